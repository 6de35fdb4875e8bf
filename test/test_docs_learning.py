"""The commands of docs/learning.md and docs/viewing_and_recording.md run as typed
(`docs_commands`; a file of their own, so that the suite's two workers share the documents)."""
from pathlib import Path

import pytest

from docs_commands import GROUPS, run_document


@pytest.mark.parametrize('document', GROUPS[Path(__file__).name])
def test_the_documents_commands_run_as_typed(document, tmp_path):
    run_document(document, tmp_path)
