"""The independent sessions of a sweep, run one after the other in this process or each as a
Ray task (Moritz et al., "Ray: A Distributed Framework for Emerging AI Applications", OSDI 2018).

A sweep (``psl bench learn`` over seeds, strategies and skill maps) is a list of `Session`s.
Each is a pure function of its settings: a module-level function and its keyword arguments,
which writes the session's run folder and returns a JSON-able record read back from it. So a
session gives the same record wherever it runs — in this process (``serial``), on this
machine's Ray cluster (``ray``, started for the sweep: as many workers as cores, nothing to
configure), or on a cluster's nodes (``ray`` with an address: ``ray start --head`` on one
machine, ``ray start --address HEAD:6379`` on the others, each started from an environment
where psl runs, `source scripts/env.sh`, with the run folders on storage every node sees).

A session that raises, or whose worker process dies, is run once more (Ray's
``max_retries``/``retry_exceptions``; serially: the same); a session that fails twice is
reported (`SweepResult.failed`) and the sweep goes on, so its table still comes out, naming
what is missing. A retried session starts again in its folder: the learner resumes from the
checkpoint its first attempt left, or starts afresh. Each record says on which node and in
which process it ran (`where`). Ray stays out of the ROS nodes and out of graph mode: a
session here is a batch-mode session. Imports no ROS.
"""
from __future__ import annotations

import contextlib
import dataclasses
import os
import socket
import sys
from typing import Any, Callable, Iterator, Sequence

RUNNERS = ('ray', 'serial')
RETRIES = 1                 # a failed session is run once more
ADDRESS_VARIABLE = 'RAY_ADDRESS'    # Ray's own: the cluster to join when --address is not given
LIVENESS_PERIOD = 10.0      # [s] between checks that the cluster is there while sessions run
CONNECT_TIMEOUT = 5.0       # [s] to reach a given cluster's head before Ray is asked to join


@dataclasses.dataclass(frozen=True)
class Session:
    """One session of a sweep: ``function(**kwargs)`` returns its record (a JSON-able dict)."""

    key: tuple                      # what the sweep calls it, e.g. (seed, row name)
    label: str                      # for the progress line, e.g. 'seed 3 bootstrap (elm)'
    function: Callable[..., dict]   # a module-level function (Ray sends it by reference)
    kwargs: dict


@dataclasses.dataclass
class SweepResult:
    records: dict[tuple, dict]      # by Session.key, of the sessions that finished
    failed: dict[tuple, str]        # by Session.key: why, after the retry
    runner: str                     # 'serial', or 'ray' and its cluster's address
    nodes: dict[str, int]           # node -> sessions it ran

    def missing(self) -> list[str]:
        """One line per failed session, for the report."""
        return [f'{key}: {reason}' for key, reason in self.failed.items()]


def where() -> dict:
    """This process's node (a Ray node's id when run as a Ray task, else the host name) and
    its process id."""
    node = socket.gethostname()
    ray = sys.modules.get('ray')          # not imported here: a serial run needs no Ray
    if ray is not None and ray.is_initialized():
        node = f'{node}:{ray.get_runtime_context().get_node_id()[:8]}'
    return {'node': node, 'pid': os.getpid()}


def _run(function: Callable[..., dict], kwargs: dict) -> dict:
    """A session's body wherever it runs: its record, and where it ran."""
    return {**function(**kwargs), 'ran_on': where()}


def run(sessions: Sequence[Session], runner: str = 'serial', address: str | None = None,
        progress: Callable[[str], None] | None = None, bar: bool | None = None) -> SweepResult:
    """Run every session; see the module docstring.

    Args:
        runner: 'serial' (this process) or 'ray'.
        address: a Ray cluster's address (``HOST:PORT``); None: $RAY_ADDRESS, else a local
            cluster started for the sweep and ended after it.
        progress: called with one line per finished (or failed) session.
        bar: a progress bar over the sessions on stderr (tqdm); None: on a terminal.

    Raises:
        ValueError: an unknown runner, or two sessions with one key.
        RuntimeError: no session finished (each failed twice: the reasons), or no Ray
            cluster at the address (`cluster`).
    """
    if runner not in RUNNERS:
        raise ValueError(f'runner must be one of {", ".join(RUNNERS)}, got {runner!r}')
    if len({s.key for s in sessions}) != len(sessions):
        raise ValueError('two sessions of the sweep have the same key')
    from tqdm import tqdm
    show = sys.stderr.isatty() if bar is None else bar
    with tqdm(total=len(sessions), desc='sessions', unit='session', disable=not show,
              file=sys.stderr) as counter:
        def done(session: Session, record: dict | None, reason: str = '') -> None:
            counter.update(1)
            if progress is not None:
                progress(f'{session.label}: FAILED ({reason})' if record is None
                         else f"{session.label}: {record.get('summary', 'done')}")
        swept = _serial(sessions, done) if runner == 'serial' else _ray(sessions, address, done)
    if sessions and not swept.records:      # a table of nothing: say why, exit non-zero
        raise RuntimeError('no session of the sweep finished: ' + '; '.join(swept.missing()))
    return swept


def _serial(sessions: Sequence[Session], done) -> SweepResult:
    records, failed = {}, {}
    for session in sessions:
        for attempt in range(1 + RETRIES):
            try:
                records[session.key] = _run(session.function, session.kwargs)
                break
            except Exception as exc:  # noqa: BLE001 - a session's failure is reported
                failed[session.key] = f'{type(exc).__name__}: {exc}'
        if session.key in records:
            failed.pop(session.key, None)
            done(session, records[session.key])
        else:
            done(session, None, failed[session.key])
    return SweepResult(records, failed, 'serial', _nodes(records))


@contextlib.contextmanager
def cluster(runner: str, address: str | None = None) -> Iterator[None]:
    """The Ray cluster of the sweeps run inside (runner 'ray'; 'serial': nothing): joined
    once, left after, so a sweep of stages (`psl_bench.sim_to_real`: the nominal sessions,
    then those that continue them) starts one local cluster, not one per stage. The given
    cluster, or a new one of this machine's cores ('local': not whatever cluster `ray start`
    left on this machine, which may be gone); on a local cluster the workers inherit this
    process's environment (psl's, scripts/env.sh). Inside an already joined cluster: that
    one.

    Raises:
        ValueError: the address is not HOST:PORT.
        RuntimeError: no cluster at the address (`check_reachable`: within CONNECT_TIMEOUT
            s), one line naming it. (ConnectionError: 'auto' and no cluster on this machine.)
    """
    if runner != 'ray':
        yield
        return
    import ray

    started = not ray.is_initialized()
    if started:
        given = address or os.environ.get(ADDRESS_VARIABLE) or 'local'
        check_reachable(given)
        ray.init(address=given, include_dashboard=False, log_to_driver=False,
                 configure_logging=False, ignore_reinit_error=True)
    try:
        yield
    finally:
        if started:
            ray.shutdown()


def check_reachable(address: str, timeout: float = CONNECT_TIMEOUT) -> None:
    """Whether a Ray cluster's head can be reached at `address` (``HOST:PORT`` or
    ``ray://HOST:PORT``; 'local' and 'auto' are Ray's to resolve): a TCP connection, within
    `timeout` s, to the address Ray itself joins (a local host name stands for its node's
    address: ``ray._private.services.canonicalize_bootstrap_address``). ``ray.init`` has no
    timeout of its own for this and retries for minutes (ray-project/ray#46863).

    Raises:
        ValueError: `address` is not HOST:PORT.
        RuntimeError: nothing answers there within `timeout` s; the message names the
            address.
    """
    if address in ('local', 'auto'):
        return
    scheme = 'ray://'
    client = address.startswith(scheme)
    host, sep, port = address[len(scheme) if client else 0:].rpartition(':')
    if not (sep and host.strip('[]') and port.isdigit() and 0 < int(port) < 65536):
        raise ValueError(f'Ray address {address!r}: give HOST:PORT (e.g. 127.0.0.1:6379, '
                         'what ray start --head prints)')
    if not client:          # Ray joins a local host name at its node's address
        from ray._private.services import canonicalize_bootstrap_address
        host, _, port = canonicalize_bootstrap_address(address).rpartition(':')
    target = (host.strip('[]'), int(port))
    try:
        with socket.create_connection(target, timeout=timeout):
            return
    except TimeoutError:
        why = f'no answer within {timeout:g} s'
    except OSError as exc:
        why = (exc.strerror or str(exc) or type(exc).__name__).lower()
    joined = '' if address.endswith(f'{target[0]}:{target[1]}') else (
        f' (joined at {target[0]}:{target[1]})')
    raise RuntimeError(f'no Ray cluster at {address}{joined}: {why}; start one there (ray '
                       f'start --head) or leave out --address and ${ADDRESS_VARIABLE} for a '
                       'cluster of this machine')


def _ray(sessions: Sequence[Session], address: str | None, done) -> SweepResult:
    import ray
    from ray.exceptions import RayError

    with cluster('ray', address):
        task = ray.remote(num_cpus=1, max_retries=RETRIES, retry_exceptions=True)(_run)
        pending = {task.remote(s.function, s.kwargs): s for s in sessions}
        records, failed = {}, {}
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=LIVENESS_PERIOD)
            if not ready:           # a long session, or a cluster that has gone
                if not any(node['Alive'] for node in ray.nodes()):
                    raise RuntimeError(f'the Ray cluster has gone; {len(pending)} sessions '
                                       'did not finish')
                continue
            session = pending.pop(ready[0])
            try:
                records[session.key] = ray.get(ready[0])
                done(session, records[session.key])
            except RayError as exc:        # raised twice, or its worker died twice
                failed[session.key] = _reason(exc)
                done(session, None, failed[session.key])
        joined = ray.get_runtime_context().gcs_address
    return SweepResult(records, failed, f'ray ({joined})', _nodes(records))


def _reason(exc: Exception) -> str:
    """One line of a Ray task's failure: the session's own exception where it raised."""
    cause = getattr(exc, 'cause', None)
    if isinstance(cause, BaseException):
        return f'{type(cause).__name__}: {cause}'
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__


def _nodes(records: dict[Any, dict]) -> dict[str, int]:
    nodes: dict[str, int] = {}
    for record in records.values():
        node = record['ran_on']['node']
        nodes[node] = nodes.get(node, 0) + 1
    return nodes
