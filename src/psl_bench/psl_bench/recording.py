"""``psl bench recording``: what recording the robot loop costs, and whether it keeps everything.

Lockstep control steps per second (the simulator's own end-of-episode figures on /diagnostics,
as in `psl_bench.graph`) over rollouts without and then with a bag recorder attached
(`psl_ros.bag_recorder.record` in a thread of this process, as ``psl demo`` records), and per
recorded topic the messages the loop published, those the bag holds and those the recorder
counted lost. Optionally with cores kept busy by spinning processes (`busy_cores`), which is
when an earlier recorder lost a third of the loop's messages.
"""
from __future__ import annotations

import os
import statistics
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from psl_bench.busy_cores import busy_cores
from psl_bench.graph import EpisodeStats
from psl_ros import names
from psl_task import DEFAULT_TASK

# topics that carry one message per state of an episode (states 0..N): the state, the
# controller's answer, the pose and the clock
PER_STATE = (names.JOINT_STATES, names.EFFORT_COMMAND, names.EE_POSE, names.CLOCK)
# topics that carry one message per rollout
PER_ROLLOUT = (names.TASK_INSTANCE, names.ROLLOUT_EVALUATION)
RECORDER_TIMEOUT = 60.0  # [s] for the recorder to take what the last rollout published


def _absolute(topic: str) -> str:
    return '/' + topic.lstrip('/')


def loop_messages(num_steps: int, rollouts: int,
                  topics: Sequence[str] = names.RECORDED_TOPICS) -> dict[str, int | None]:
    """Messages each of `topics` (fully qualified) carries over `rollouts` lockstep episodes
    of `num_steps` control periods: one per state 0..N (`PER_STATE`: the controller answers
    every state, the last one too), one per rollout (`PER_ROLLOUT`), None for any other
    topic (e.g. the scene, whose count depends on its rate)."""
    out: dict[str, int | None] = {}
    for topic in topics:
        if topic in PER_STATE:
            out[_absolute(topic)] = rollouts * (num_steps + 1)
        elif topic in PER_ROLLOUT:
            out[_absolute(topic)] = rollouts
        else:
            out[_absolute(topic)] = None
    return out


def _rates(episodes: list[dict]) -> dict:
    """Median and slowest steps/s of the simulator's end-of-episode figures."""
    rates = [float(e['steps_per_second']) for e in episodes]
    return {'episodes': len(rates), 'steps_per_second_median': statistics.median(rates),
            'steps_per_second_min': min(rates)}


def _wait_episodes(stats: EpisodeStats, count: int, timeout: float = 30.0) -> None:
    """Until the simulator has reported `count` finished episodes on /diagnostics."""
    deadline = time.monotonic() + timeout
    while len(stats.done) < count:
        if time.monotonic() > deadline:
            raise RuntimeError(f'{len(stats.done)} of {count} episodes reported on '
                               '/diagnostics')
        time.sleep(0.02)


def _record_rollouts(client, bag: Path, topics: Sequence[str],
                     expected: dict[str, int | None], run_rollouts) -> tuple:
    """Record `topics` into `bag` in a thread while `run_rollouts(client)` runs; end the
    recording once the recorder has taken (or counted lost) every message `expected` says
    the loop published, or after RECORDER_TIMEOUT. Returns the Recording and the seconds the
    recorder needed after the last rollout (None: it timed out)."""
    from psl_ros.bag_recorder import record

    complete, stop, out = threading.Event(), threading.Event(), {}

    def progress(so_far) -> None:
        if all(so_far.counts.get(t, 0) + so_far.lost.get(t, 0) >= n
               for t, n in expected.items() if n is not None):
            complete.set()

    def recording() -> None:
        try:
            out['recording'] = record(bag, list(topics), stop=stop, discovery_timeout=2.0,
                                      progress=progress)
        except Exception as exc:  # noqa: BLE001 - raised in the calling thread
            out['error'] = exc

    recorder = threading.Thread(target=recording)
    recorder.start()
    try:
        # every topic: the simulator builds the pose, the clock and the scene only for
        # subscribers it has matched
        client.wait_for_subscribers(topics)
        run_rollouts(client)
        start = time.perf_counter()
        wait = time.perf_counter() - start if complete.wait(RECORDER_TIMEOUT) else None
    finally:
        stop.set()
        recorder.join()
    if 'error' in out:
        raise out['error']
    return out['recording'], wait


def measure(task_name: str = DEFAULT_TASK, rollouts: int = 5, busy: int = 0,
            topics: Sequence[str] = names.RECORDED_TOPICS, rounds: int = 3) -> dict:
    """Lockstep steps/s without and with the recorder, and the messages kept and lost.

    One graph; each round runs `rollouts` rollouts (random task instances, the default
    policy) without a recorder, then `rollouts` more while `topics` are recorded into a new
    bag. A recording ends once the recorder has taken every message the loop published (or
    after RECORDER_TIMEOUT). Several rounds pair the phases in time on a shared machine.

    Args:
        task_name: The task (name or YAML path).
        rollouts: Rollouts per phase and round (>= 1).
        busy: Cores kept busy by spinning processes during the whole run.
        topics: Topics to record; what the loop publishes is known for `PER_STATE` and
            `PER_ROLLOUT` (None for others: only what the bags hold and what was lost).
        rounds: Rounds of both phases (>= 1).

    Returns:
        The report: steps/s of both phases (medians over all their episodes) and the median
        of the rounds' ratios; per topic published / in the bags / counted lost / missing,
        the totals; the recorder's longest wait after a round's last rollout.

    Raises:
        ValueError: ``rollouts``, ``rounds`` < 1 or ``busy`` < 0.
        RuntimeError: The graph did not come up or a rollout failed.
        TimeoutError: The recorder did not subscribe in time.
    """
    from psl_controller.policy import policy_for
    from psl_ros.client import RosClient
    from psl_ros.graph import Graph
    from psl_task.task import load_task, task_id

    if rollouts < 1 or rounds < 1 or busy < 0:
        raise ValueError(f'need rollouts >= 1, rounds >= 1 and busy >= 0, got {rollouts}, '
                         f'{rounds} and {busy}')
    task = load_task(task_name)
    expected = loop_messages(task.num_steps, rollouts, topics)
    if expected.get(_absolute(names.TASK_INSTANCE)) is not None:
        expected[_absolute(names.TASK_INSTANCE)] += 1   # latched: the episode before, too
    theta = policy_for(task).default_theta
    rng = np.random.default_rng(0)

    def run_rollouts(client) -> None:
        for _ in range(rollouts):
            result = client.rollout(task_id(task), task.sample_tau(rng), theta)
            if not result.success:
                raise RuntimeError(result.message)

    recordings, waits, phases = [], [], []   # phases: (episodes without, episodes with)
    with Graph(task=task_id(task), mode='lockstep') as graph, busy_cores(busy), \
            tempfile.TemporaryDirectory() as folder:
        graph.wait_ready()
        with RosClient() as client:
            stats = EpisodeStats(client.node)
            time.sleep(0.5)
            for index in range(rounds):
                done = len(stats.done)
                run_rollouts(client)
                _wait_episodes(stats, done + rollouts)
                recording, wait = _record_rollouts(
                    client, Path(folder) / f'bag{index}', topics, expected, run_rollouts)
                _wait_episodes(stats, done + 2 * rollouts)
                recordings.append(recording)
                waits.append(wait)
                phases.append((stats.done[done:done + rollouts],
                               stats.done[done + rollouts:done + 2 * rollouts]))
    without = _rates([e for a, _ in phases for e in a])
    with_ = _rates([e for _, b in phases for e in b])
    ratios = [_rates(b)['steps_per_second_median'] / _rates(a)['steps_per_second_median']
              for a, b in phases]
    topics_report = {}
    for topic, n in expected.items():
        in_bag = sum(r.counts.get(topic, 0) for r in recordings)
        published = None if n is None else n * rounds
        topics_report[topic] = {
            'published': published, 'in_bag': in_bag,
            'lost_counted': sum(r.lost.get(topic, 0) for r in recordings),
            'missing': None if published is None else published - in_bag}
    return {
        'task': task.name, 'machine_cores': os.cpu_count(), 'busy_cores': busy,
        'rollouts': rollouts, 'rounds': rounds, 'steps_per_episode': task.num_steps,
        'without_recorder': without, 'with_recorder': with_,
        'with_over_without': statistics.median(ratios), 'round_ratios': ratios,
        'recorder_complete': all(w is not None for w in waits),
        'recorder_wait_s': max((w for w in waits if w is not None), default=None),
        'topics': topics_report,
        'missing': sum(t['missing'] or 0 for t in topics_report.values()),
        'lost_counted': sum(r.total_lost for r in recordings),
    }


def format_report(report: dict) -> str:
    """The report as a table: steps/s of both phases, then messages per topic."""
    a, b = report['without_recorder'], report['with_recorder']
    lines = [f"lockstep {report['task']}: {report['rounds']} x {report['rollouts']} rollouts "
             f"of {report['steps_per_episode']} steps per phase, {report['busy_cores']} of "
             f"{report['machine_cores']} cores kept busy",
             f"  without recorder {a['steps_per_second_median']:7.0f} steps/s median "
             f"(min {a['steps_per_second_min']:.0f})",
             f"  with recorder    {b['steps_per_second_median']:7.0f} steps/s median "
             f"(min {b['steps_per_second_min']:.0f}); median ratio of the rounds "
             f"{report['with_over_without']:.2f}",
             f"  {'topic':22s}{'published':>11s}{'in bag':>9s}{'lost (counted)':>16s}"
             f"{'missing':>9s}"]
    for topic, t in report['topics'].items():
        published, missing = ('-' if n is None else str(n)
                              for n in (t['published'], t['missing']))
        lines.append(f"  {topic:22s}{published:>11s}{t['in_bag']:9d}"
                     f"{t['lost_counted']:16d}{missing:>9s}")
    if report['missing'] == 0 and report['lost_counted'] == 0:
        lines.append('  every message is in the bag')
    else:
        lines.append(f"  {report['missing']} messages missing, {report['lost_counted']} "
                     'counted lost by the recorder')
    return '\n'.join(lines) + '\n'
