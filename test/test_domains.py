"""The suite's ROS domains (the root conftest.py): a domain one process holds is claimed by no
other until that process ends, however it ends; private domains come from the other end."""
import importlib.util
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CLAIM = ('import importlib.util, sys, time; spec = importlib.util.spec_from_file_location('
         f'"domains", {str(ROOT / "conftest.py")!r}); '
         'm = importlib.util.module_from_spec(spec); spec.loader.exec_module(m); '
         'print(m.claim_domain(), flush=True); time.sleep(120)')


def fresh_claims(folder: Path, monkeypatch):
    """A new instance of conftest.py's claims (none held yet) whose lock files are in
    `folder` (this test's own, not the system's temporary folder)."""
    monkeypatch.setattr(tempfile, 'tempdir', str(folder))
    spec = importlib.util.spec_from_file_location('psl_test_domains', ROOT / 'conftest.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def release(module) -> None:
    for fd in module._claimed.values():
        os.close(fd)


def test_a_domain_another_process_holds_is_not_claimed_until_that_process_dies(
        tmp_path, monkeypatch):
    monkeypatch.setenv('PSL_TEST_DOMAIN_ID', '5')
    holder = subprocess.Popen([sys.executable, '-c', CLAIM], stdout=subprocess.PIPE, text=True,
                              env={**os.environ, 'TMPDIR': str(tmp_path)})
    claims = []
    try:
        assert holder.stdout.readline().strip() == '5'
        first = fresh_claims(tmp_path, monkeypatch)
        claims.append(first)
        assert first.claim_domain() == 6                    # 5 is held: the next one
        assert first.claim_domain(private=True) == first.DOMAINS[-1]
        assert first.claim_domain(private=True) == first.DOMAINS[-2]
        second = fresh_claims(tmp_path, monkeypatch)         # another process's view
        claims.append(second)
        assert second.claim_domain() == 7
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=30)
        holder.stdout.close()
    third = fresh_claims(tmp_path, monkeypatch)
    claims.append(third)
    assert third.claim_domain() == 5                        # released by the kernel
    for module in claims:
        release(module)


def test_the_domains_leave_out_a_users_own(tmp_path, monkeypatch):
    """0 (ROS's default) and 42 (scripts/env.sh's): where a user's graph runs by default."""
    module = fresh_claims(tmp_path, monkeypatch)
    assert 0 not in module.DOMAINS and 42 not in module.DOMAINS
    monkeypatch.setenv('PSL_TEST_DOMAIN_ID', '41')
    try:
        assert [module.claim_domain() for _ in range(2)] == [41, 43]
    finally:
        release(module)
