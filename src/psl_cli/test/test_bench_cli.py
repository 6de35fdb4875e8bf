"""``psl bench cli`` (psl_bench.cli_latency): it starts a skill memory, times ``psl memory
info`` as processes beside its references, ends the memory, and reports every part. No
assertion on how long anything takes (a shared machine): only that each part was measured and
that the parts add up."""
import json

import pytest

from psl_bench import cli_latency
from psl_cli.main import main

PARTS = ('total_s', 'answer_s', 'after_answer_s', 'unanswered_s', 'in_process_answer_s',
         'in_process_close_s')


def test_the_bench_measures_each_part_and_prints_them(capsys):
    assert main(['bench', 'cli', '--runs', '2', '--json']) == 0
    report = json.loads(capsys.readouterr().out)
    assert report['runs'] == 2 and report['command'] == 'psl memory info'
    for part in PARTS:
        values = report[part]['values']
        assert len(values) == 2 and all(v > 0 for v in values), (part, values)
        assert report[part]['min'] <= report[part]['median'] <= report[part]['max']
    for total, answer, after in zip(*(report[k]['values']
                                      for k in ('total_s', 'answer_s', 'after_answer_s'))):
        assert total == pytest.approx(answer + after)
    table = cli_latency.format_report(report)
    assert 'after the answer' in table and 'nothing answers' in table


def test_a_bad_setting_is_refused():
    with pytest.raises(ValueError):
        cli_latency.measure(runs=0)
