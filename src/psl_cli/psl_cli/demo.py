"""``psl demo`` (what ``make demo`` runs): the whole robot loop on the embedded default task.

Starts the graph (every node its own process), records the loop's topics into a rosbag2
(MCAP) bag, rolls out the demonstration's policy over a few obstacle placements, has the
learner node learn the skill (batch mode, bootstrap, 30 random instances; the skill lives in
the skill_memory node), rolls out PS(tau) from the memory on the same placements (never trained
on: zero-shot), prints both tables and ends every process it started.
"""
from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np

from psl_ros.graph import Graph
from psl_controller.policy import policy_for
from psl_ros import names
from psl_ros.bag_recorder import read_bag_summary, record
from psl_ros.client import RosClient, evaluation_dict
from psl_task.task import load_task, task_id



def placements(task, count: int) -> list[np.ndarray]:
    """`count` task instances spread over the ranges: the first parameter swept from low to
    high, the others alternating between their defaults and their upper ends."""
    low, high, default = task.tau_low, task.tau_high, task.tau_default
    out = []
    for i, s in enumerate(np.linspace(0.0, 1.0, count)):
        tau = default.copy() if i % 2 == 0 else high.copy()
        tau[0] = low[0] + s * (high[0] - low[0])
        out.append(tau)
    return out


LEARN_TASKS = 30


def run_demo(task: str, out: Path, positions: int = 5) -> int:
    definition = load_task(task)
    theta = policy_for(definition).default_theta
    out.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime('%Y%m%d-%H%M%S')
    bag = out / f'bag-{stamp}'
    rows, learned = [], []
    with Graph(task=task_id(definition), mode='lockstep') as graph:
        print('started ' + ', '.join(f'{p.name} (pid {p.pid})' for p in graph.processes),
              flush=True)
        graph.wait_ready()
        stop = threading.Event()
        recorded: dict[str, int] = {}       # messages per topic so far (the recorder's thread)
        recorder = threading.Thread(target=record, args=(bag, names.RECORDED_TOPICS),
                                    kwargs={'stop': stop, 'discovery_timeout': 2.0,
                                            'progress': lambda r: recorded.update(r.counts)})
        recorder.start()
        try:
            with RosClient() as client:
                client.wait_for_subscribers([t for t in names.RECORDED_TOPICS
                                             if t in names.LOOP_TOPICS])
                for tau in placements(definition, positions):
                    result = client.rollout(task_id(definition), tau, theta)
                    if not result.success:
                        print(f'rollout at tau={tau.tolist()} failed: {result.message}')
                        return 1
                    rows.append(evaluation_dict(result.evaluation))
                print(f'learning the skill over {LEARN_TASKS} random instances (learner node, '
                      'batch mode, bootstrap) ...', flush=True)
                session = client.learn(timeout=600, task=task_id(definition),
                                       strategy='bootstrap', num_tasks=LEARN_TASKS,
                                       max_rollouts_per_task=200, seed=0, mode='batch',
                                       output_dir=str((out / f'skill-{stamp}').resolve()))
                if not session.success:
                    print(f'learning failed: {session.message}')
                    return 1
                print(f'learned: {session.message}; metrics in {session.metrics_path}')
                for tau in placements(definition, positions):
                    answer = client.memory('query', skill=definition.name,
                                           tau=[float(x) for x in tau])
                    result = client.rollout(task_id(definition), tau, np.asarray(answer.theta))
                    if not (answer.success and result.success):
                        print(f'skill rollout at tau={tau.tolist()} failed: '
                              f'{answer.message} {result.message}')
                        return 1
                    learned.append(evaluation_dict(result.evaluation))
        finally:
            # each rollout's evaluation, the last message of its episode, in the bag too
            evaluation = '/' + names.ROLLOUT_EVALUATION
            deadline = time.monotonic() + 10.0
            while (recorded.get(evaluation, 0) < len(rows) + len(learned)
                   and time.monotonic() < deadline and recorder.is_alive()):
                time.sleep(0.01)
            stop.set()
            recorder.join()
    tau_names = definition.tau_names
    header = ''.join(f'{n:>17s}' for n in tau_names) + f'{"reward":>10s}{"fulfilled":>11s}' \
        f'{"goal err [m]":>14s}{"penetration [m]":>17s}{"tracking [rad]":>16s}'
    for title, table in ((f'the demonstration policy on task {definition.name!r}', rows),
                         ('the learned skill, theta = PS(tau) from the skill_memory node '
                          '(zero-shot)', learned)):
        print(f'\n{title}: {sum(r["fulfilled"] for r in table)} of {len(table)} fulfilled')
        print(header)
        for row in table:
            c = row['components']
            print(''.join(f'{v:17.3f}' for v in row['tau']) + f'{row["reward"]:10.3f}'
                  f'{str(row["fulfilled"]):>11s}{c["goal_error"]:14.4f}'
                  f'{c["penetration"]:17.4f}{c["tracking_error"]:16.4f}')
    print(f'\nbag {bag} (rosbag2, MCAP):')
    for topic, (msgtype, count) in sorted(read_bag_summary(bag).items()):
        print(f'  {topic:22s} {msgtype:34s} {count:6d} messages')
    print('all processes ended')
    return 0
