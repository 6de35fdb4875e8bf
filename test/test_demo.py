"""`psl demo` (what `make demo` runs) end to end: the graph as processes, the demonstration and
the learned skill on the same placements, a bag of the loop's topics, nothing left behind."""
import re
import subprocess
import sys

from psl_ros import names
from psl_ros.bag_recorder import read_bag_summary
from psl_ros.graph import pid_alive


def test_the_demo_learns_records_and_ends_its_processes(tmp_path):
    done = subprocess.run([sys.executable, '-m', 'psl_cli.main', 'demo', '--out',
                           str(tmp_path), '--positions', '3'],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    out = done.stdout
    pids = [int(pid) for pid in re.findall(r'\(pid (\d+)\)', out)]
    assert len(pids) == 6 and not [pid for pid in pids if pid_alive(pid)]
    demonstration = re.search(r'the demonstration policy .*: (\d) of 3 fulfilled', out)
    learned = re.search(r'the learned skill, .*: (\d) of 3 fulfilled', out)
    assert demonstration and learned, out
    assert int(learned.group(1)) >= int(demonstration.group(1))
    assert int(learned.group(1)) == 3                 # the skill solves them zero-shot
    bags = list(tmp_path.glob('bag-*'))
    assert len(bags) == 1
    summary = read_bag_summary(bags[0])
    assert set(summary) == {'/' + t.lstrip('/') for t in names.RECORDED_TOPICS}
    assert all(count > 0 for _, count in summary.values())
    assert summary['/rollout_evaluation'][1] == 6      # 3 demonstration + 3 skill rollouts
