#!/bin/bash
# A two-node Ray cluster on this machine, its nodes started as a cluster's are (each a
# process of its own), and a psl bench learn sweep on it; the report in ./two_nodes.json.
# Run from a folder of your choice: scripts/ray_two_nodes.sh
source "$(dirname "${BASH_SOURCE[0]}")/env.sh"

IP=$(hostname -I | cut -d' ' -f1)
PORT=6393
nice -n 19 ray start --head --port=$PORT --num-cpus=1 --include-dashboard=false --block > head.log 2>&1 &
HEAD=$!
for i in $(seq 100); do grep -q "Ray runtime started" head.log && break; sleep 0.2; done
nice -n 19 ray start --address=$IP:$PORT --num-cpus=1 --block > node.log 2>&1 &
NODE=$!
for i in $(seq 100); do grep -q "Ray runtime started" node.log && break; sleep 0.2; done
ARGS="--task reach_over_obstacle --strategies scratch bootstrap --seeds 0 1 2 3 4 5 6 7 8 9"
s=$(date +%s.%N)
nice -n 19 psl bench learn $ARGS -o two_nodes --address $IP:$PORT --json > two_nodes.json 2> two_nodes.err
e=$(date +%s.%N)
echo "two nodes $(echo "$e - $s" | bc)" >> two_nodes_time.txt
kill $NODE $HEAD; wait $NODE $HEAD 2>/dev/null
