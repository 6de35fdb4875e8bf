"""The documented commands run as typed (`docs_commands`): README.md and the short guides here
(`GROUPS`), the others in test_docs_*.py; and the marks of every document: each command the
docs do not run is a skipped test with its reason, and has its fast form or names its test."""
from pathlib import Path

import pytest

from docs_commands import (DOCUMENTS, GROUPS, ROOT, TEST_FILE, Command, commands,
                           fast_form_missing, run_document)

MARKED_NOT_RUN = [c for d in DOCUMENTS for block in commands(d) for c in block if c.not_run]


@pytest.mark.parametrize('document', GROUPS[Path(__file__).name])
def test_the_documents_commands_run_as_typed(document, tmp_path):
    run_document(document, tmp_path)


def test_every_document_with_commands_is_run_by_one_test_file():
    grouped = [d for documents in GROUPS.values() for d in documents]
    with_commands = [d for d in DOCUMENTS if any(c.not_run is None for block in commands(d)
                                                  for c in block)]
    assert sorted(grouped) == sorted(set(grouped)), 'a document in two groups'
    assert set(with_commands) <= set(grouped), set(with_commands) - set(grouped)
    assert all((Path(__file__).parent / name).is_file() for name in GROUPS)


@pytest.mark.parametrize('document', DOCUMENTS)
def test_every_command_not_run_has_a_fast_form_or_names_its_test(document):
    missing = [c for block in commands(document) for c in fast_form_missing(block)]
    assert not missing, '\n'.join(
        f'{c.where} `{c.text}`: not run, and neither is the next command of its block (its '
        'fast form) nor does its reason name the test that runs it' for c in missing)
    for block in commands(document):
        for c in block:
            if c.not_run and (name := _named_test(c)):
                assert (ROOT / name).is_file(), f'{c.where} names {name}, which does not exist'


def _named_test(command: Command) -> str | None:
    found = TEST_FILE.search(command.not_run or '')
    return found.group(1) if found else None


@pytest.mark.parametrize('command', MARKED_NOT_RUN, ids=[c.where for c in MARKED_NOT_RUN])
def test_a_command_the_docs_mark_as_not_run(command):
    pytest.skip(f'{command.where} `{command.words[0]} {" ".join(command.words[1:3])}`: '
                f'{command.not_run}')




def test_a_block_is_read_as_a_reader_types_it(tmp_path):
    (tmp_path / 'doc.md').write_text('''Prose with `psl up` inline is no command.

```bash
# a comment line is prose
psl up --task T \\
       --view            # continued: one command
psl learn --tasks 3      # its comment
      # goes on here [prints: 96 rollouts over 30 tasks]
psl bench learn   # [not run by the docs test: minutes]
psl bench learn --tasks 2
python - <<'PY'
print('a here-document')
PY
psl memory load x.npz   # [exits 2]
```

```yaml
psl: not a command
```
''')
    (block,) = commands('doc.md', root=tmp_path)
    assert [c.line for c in block] == [5, 7, 9, 10, 11, 14]
    up, learn, bench, fast, heredoc, refused = block
    assert up.words == ['psl', 'up', '--task', 'T', '--view'] and up.ready
    assert learn.prints == '96 rollouts over 30 tasks' and learn.not_run is None
    assert bench.not_run == 'minutes' and fast.not_run is None
    assert fast_form_missing(block) == []
    assert heredoc.text.endswith("print('a here-document')\nPY") and heredoc.ready is None
    assert refused.exits == 2 and up.exits == 0
    assert fast_form_missing([bench]) == [bench]                # no fast form after it


def test_a_quoted_figure_holds_within_its_tolerance_and_its_words_exactly():
    from docs_commands import FIGURE_RTOL, figure_printed

    out = 'task 30/30\n96 rollouts over 30 tasks; held-out zero-shot success 95 % (mean -0.03)'
    assert figure_printed('96 rollouts over 30 tasks; held-out zero-shot success 95 %', out)
    assert figure_printed('100 rollouts over  30 tasks', out)                # within 10 %
    assert not figure_printed(f'{96 * (1 + 2 * FIGURE_RTOL):.0f} rollouts over 30 tasks', out)
    assert not figure_printed('96 rollouts over 30 instances', out)          # other words
    assert figure_printed('(mean -0.03)', out) and not figure_printed('(mean 0.03)', out)
