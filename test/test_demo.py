"""`psl demo` (what `make demo` runs) end to end: the graph as processes, the demonstration and
the learned skill on the same placements, a bag of the loop's topics, nothing left behind."""
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

from psl_ros import names
from psl_ros.bag_recorder import read_bag_summary
from psl_ros.graph import NODES, NodeHandle

DEMO_TIMEOUT = 600.0        # s, a backstop for the whole demo (it takes seconds)
README = Path(__file__).resolve().parent.parent / 'README.md'


def quoted_figures() -> dict[str, int]:
    """The figures README.md quotes beside `make demo` (its quick start), as whole numbers."""
    text = README.read_text()
    comment = text[text.index('make demo   #'):text.index('make test   #')]
    patterns = {'demonstration': r'\((\d) of 5 fulfilled\)',
                'held_out': r'(\d+) % of 20 held-out ones zero-shot',
                'skill': r'\((\d) of 5 zero-shot\)'}
    found = {name: re.search(pattern, ' '.join(comment.split()))
             for name, pattern in patterns.items()}
    assert all(found.values()), f'README.md no longer quotes the demo as this test reads it: ' \
        f'{comment}'
    return {name: int(m.group(1)) for name, m in found.items()}


def test_the_demo_learns_records_and_ends_its_processes(tmp_path):
    log_path = tmp_path / 'demo.log'
    with open(log_path, 'w') as log:
        demo = subprocess.Popen([sys.executable, '-m', 'psl_cli.main', 'demo', '--out',
                                 str(tmp_path)],
                                stdout=log, stderr=subprocess.STDOUT, text=True,
                                start_new_session=True)
    nodes: list[NodeHandle] = []
    try:
        # its nodes, held from the moment it prints their PIDs (one line, flushed)
        deadline = time.monotonic() + DEMO_TIMEOUT
        while not nodes:
            ended = demo.poll() is not None
            started = re.search(r'^started (.*)\n', log_path.read_text(), re.MULTILINE)
            if started:
                nodes = [NodeHandle(label, int(pid), demo.pid) for label, pid in
                         re.findall(r'(\S+) \(pid (\d+)\)', started.group(1))]
            elif ended:
                break
            assert time.monotonic() < deadline, f'psl demo printed: {log_path.read_text()}'
            time.sleep(0.05)
        demo.wait(timeout=max(0.0, deadline - time.monotonic()))
    finally:
        try:
            if demo.poll() is None:           # Ctrl-C: the demo ends its graph, then itself
                os.killpg(demo.pid, signal.SIGINT)      # not reaped: its group still
                try:
                    demo.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    os.killpg(demo.pid, signal.SIGKILL)
                    demo.wait()
        finally:
            left = [node.label for node in nodes if node.alive()]
            for node in nodes:
                node.kill()
                node.close()
    out = log_path.read_text()
    assert demo.returncode == 0, out
    assert len(nodes) == len(NODES) and not left, (left, out)
    demonstration = re.search(r'the demonstration policy .*: (\d) of 5 fulfilled', out)
    learned = re.search(r'the learned skill, .*: (\d) of 5 fulfilled', out)
    held_out = re.search(r'held-out zero-shot success (\d+) %', out)
    assert demonstration and learned and held_out, out
    # the figures README.md quotes: the seeds are fixed, but another CPU's last bits of
    # floating point may turn a search another way: one placement of five, 10 points of 100
    quoted = quoted_figures()
    assert int(demonstration.group(1)) == quoted['demonstration'], out    # no learning in it
    assert abs(int(learned.group(1)) - quoted['skill']) <= 1, (quoted, out)
    assert abs(int(held_out.group(1)) - quoted['held_out']) <= 10, (quoted, out)
    # the skill, never trained on these placements, solves more of them than the
    # demonstration does (the placements at the ends of the range are the hardest, and
    # learning sessions differ in them)
    assert int(learned.group(1)) > int(demonstration.group(1))
    bags = list(tmp_path.glob('bag-*'))
    assert len(bags) == 1
    summary = read_bag_summary(bags[0])
    assert set(summary) == {'/' + t.lstrip('/') for t in names.RECORDED_TOPICS}
    assert all(count > 0 for _, count in summary.values())
    assert summary['/rollout_evaluation'][1] == 10     # 5 demonstration + 5 skill rollouts
