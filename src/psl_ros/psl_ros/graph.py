"""Start the psl node graph as separate processes and end exactly those processes.

What a launch file does on a full ROS 2 install (there is no ``ros2 launch`` among the wheels):
the plan of the psl nodes (package and executable names, namespaces, parameters), their
processes and their readiness. It names the nodes but imports none of them, so the command
line, the benchmarks and the tests start graphs alike. Every node is its own executable
(``install/<package>/lib/<package>/<executable>``, what ``ros2 run`` would start); `Graph`
starts them with ROS arguments (namespace, parameters), keeps their PIDs, writes each one's
output to a log file, and ends them by PID: SIGINT, then SIGTERM, then SIGKILL. If one dies,
`Graph.dead` and `Graph.describe_death` say which one and its last output.

The logs go to the folder given as `log_dir`, else to a new folder named by the start time
under `PSL_LOG_DIR` (environment), else under ``log/graph`` in the current working directory
(`default_log_dir`).
"""
from __future__ import annotations

import dataclasses
import os
import select
import signal
import subprocess
import time
from pathlib import Path

from psl_ros.shared_memory import remove_stale

LOG_ROOT_VARIABLE = 'PSL_LOG_DIR'       # environment: where the graphs' log folders go
DEFAULT_LOG_ROOT = Path('log') / 'graph'  # ... when unset: relative to the working directory
SIM_MODES = ('lockstep', 'realtime')     # how the simulator advances (psl_sim/sim_node.py)
NODES = (  # (name, package, executable); the first two are the 'sim' robot's
    ('sim', 'psl_sim', 'sim'),
    ('pd_controller', 'psl_controller', 'pd_controller'),
    ('dmp_executor', 'psl_controller', 'dmp_executor'),
    ('reward_evaluator', 'psl_optimizer', 'reward_evaluator'),
    ('skill_memory', 'psl_memory', 'skill_memory'),
    ('learner', 'psl_optimizer', 'learner'),
)
# the nodes of one rollout worker: with Graph(workers=N) each worker runs under <ns>/worker<k>
WORKER_NODES = ('sim', 'robot', 'pd_controller', 'dmp_executor', 'reward_evaluator')
SIM, PD_CONTROLLER = NODES[0], NODES[1]
STANDARD_ROBOT = ('robot', 'psl_sim', 'standard_robot')
VIEW = ('view', 'psl_ros', 'view')     # the graph live in Foxglove (psl up --view)


@dataclasses.dataclass(frozen=True)
class RobotKind:
    """What a graph's loop runs on: the robot-side nodes psl starts, the controller the
    executor drives (a JointTrajectoryController's node, relative to the worker's namespace)
    and the clock of its episodes (the executor's ``clock``)."""

    name: str
    doc: str
    nodes: tuple[tuple[str, str, str], ...]
    controller: str
    clock: str
    node_params: tuple[tuple[str, dict], ...] = ()      # (node, parameters) of psl's nodes
    own_controller: bool = False    # the robot may bring its own controller (given by name)

    def robot_nodes(self, controller: str) -> tuple[tuple[str, str, str], ...]:
        """The nodes psl starts for the robot; a controller given by the user (a robot's own
        JointTrajectoryController) replaces psl's pd_controller."""
        return tuple(n for n in self.nodes if not (controller and n is PD_CONTROLLER))


ROBOT_KINDS = {kind.name: kind for kind in (
    RobotKind('sim', "psl's simulator (MuJoCo; lockstep or realtime) and psl's controller; the "
              'simulator runs each episode (teleport or drive)', (SIM, PD_CONTROLLER),
              'pd_controller', 'simulator', (('pd_controller', {'state_timeout': 0.0}),)),
    RobotKind('standard', "psl's simulator playing a ros2_control robot on the wall clock: "
              'joint_states and its own JointTrajectoryController (the PD + feed-forward '
              'law in its loop; noise, latency, model error)', (STANDARD_ROBOT,),
              'standard_robot', 'robot'),
    RobotKind('external', 'your robot, running already: its JointTrajectoryController '
              "(--controller), or for a robot that takes torques only psl's pd_controller "
              'on its effort topic (watchdog on)', (PD_CONTROLLER,), 'pd_controller',
              'robot', own_controller=True),
)}
ROBOTS = tuple(ROBOT_KINDS)


def pid_alive(pid: int) -> bool:
    """True while the process runs (a zombie, ended but not yet reaped, counts as ended)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        with open(f'/proc/{pid}/stat') as f:
            return f.read().rsplit(')', 1)[-1].split()[0] != 'Z'
    except OSError:
        return False


class NodeHandle:
    """A psl node that another process (psl up, psl demo) started and printed the PID of,
    held by a pidfd from the moment the PID is read: checked then to be that process's child
    running the node's executable, it can later be signalled and watched without ever
    reaching another process that has reused the PID meanwhile."""

    def __init__(self, label: str, pid: int, parent: int):
        self.label, self.pid = label, pid
        try:
            self._fd = os.pidfd_open(pid)
        except ProcessLookupError:          # ended and reaped already: nothing to hold
            self._fd = None
            return
        try:
            with open(f'/proc/{pid}/status') as f:
                ppid = int(next(line for line in f if line.startswith('PPid:')).split()[1])
            with open(f'/proc/{pid}/cmdline', 'rb') as f:
                cmdline = f.read().decode(errors='replace').split('\0')
        except OSError:
            ppid, cmdline = None, []
        # read with the pidfd held: if its process runs still, what was read was its own (an
        # empty command line: it is exiting, its memory already released)
        if self.alive() and any(cmdline):
            package, executable = next((p, e) for n, p, e in NODES + (STANDARD_ROBOT, VIEW)
                                       if n == label.rsplit('/', 1)[-1])
            if ppid != parent or not any(arg.endswith(f'/lib/{package}/{executable}')
                                         for arg in cmdline):
                self.close()
                raise AssertionError(f'pid {pid} is not {label} of pid {parent}: child of '
                                     f'{ppid}, running {" ".join(cmdline)}')

    def alive(self) -> bool:
        """False once it has ended (a zombie not reaped yet has ended)."""
        return (self._fd is not None
                and not select.select([self._fd], [], [], 0)[0])    # readable: it ended

    def kill(self, sig: int = signal.SIGKILL) -> bool:
        """Send `sig`; False if the node had ended already."""
        if self._fd is None:
            return False
        try:
            signal.pidfd_send_signal(self._fd, sig)
        except ProcessLookupError:
            return False
        return True

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def log_root() -> Path:
    """The folder under which graphs put their log folders: ``$PSL_LOG_DIR``, else
    ``./log/graph`` (absolute, from the current working directory)."""
    return Path(os.environ.get(LOG_ROOT_VARIABLE) or DEFAULT_LOG_ROOT).expanduser().resolve()


def default_log_dir(suffix: str = '') -> Path:
    """A graph's log folder when none is given: ``log_root()/<start time><suffix>``."""
    return log_root() / (time.strftime('%Y%m%d-%H%M%S') + suffix)


def _prefixes() -> list[Path]:
    return [Path(p) for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]


def find_executable(package: str, executable: str) -> Path:
    for prefix in _prefixes():
        path = prefix / 'lib' / package / executable
        if path.is_file() and os.access(path, os.X_OK):
            return path
    raise FileNotFoundError(
        f'executable {executable!r} of package {package!r} not found on AMENT_PREFIX_PATH; '
        'did you source scripts/env.sh?')


@dataclasses.dataclass
class NodeProcess:
    name: str
    process: subprocess.Popen
    log_path: Path
    cmd: list[str] = dataclasses.field(default_factory=list)
    worker: str = ''                # the rollout worker's namespace ('' = not a worker's node)

    @property
    def pid(self) -> int:
        return self.process.pid

    def tail(self, lines: int = 15) -> str:
        try:
            return '\n'.join(self.log_path.read_text(errors='replace').splitlines()[-lines:])
        except OSError:
            return ''


class Graph:
    """The robot loop (sim, controller, executor, evaluator) as separate processes.

    With ``workers=N`` (N >= 1) the loop's nodes run N times, under ``<namespace>/worker<k>``,
    and the learner spreads a population over them (its ``workers`` parameter); the skill
    memory and the learner run once, in ``<namespace>``."""

    def __init__(self, task: str = '', mode: str = SIM_MODES[0],
                 namespace: str = '', log_dir: str | Path | None = None,
                 nodes: tuple = NODES, extra_params: dict[str, dict] | None = None,
                 workers: int = 0, reset: str = '',
                 launch_prefix: dict[str, list[str]] | None = None,
                 robot: str = ROBOTS[0], robot_topics: dict[str, str] | None = None,
                 view_port: int | None = None, controller: str = ''):
        if mode not in SIM_MODES:
            raise ValueError(f'mode must be one of {SIM_MODES}, got {mode!r}')
        if robot not in ROBOT_KINDS:
            raise ValueError(f'robot must be one of {", ".join(ROBOTS)}, got {robot!r}')
        self.kind = kind = ROBOT_KINDS[robot]
        if controller and not kind.own_controller:
            raise ValueError(f'robot {robot!r} runs its controller itself; a controller of '
                             f'your robot is given with robot '
                             f'{next(k for k in ROBOT_KINDS.values() if k.own_controller).name}')
        # the robot's topics, by psl's name (joint_states, effort_command): remaps of the loop
        self.robot, self.robot_topics = robot, dict(robot_topics or {})
        self.controller = controller or kind.controller
        # a loop (an executor) runs on the robot kind's nodes, first, in place of any
        # robot-side node of `nodes`; a graph without one starts what it is given
        self.loop = any(name == 'dmp_executor' for name, *_ in nodes)
        if self.loop:
            robot_side = {SIM, PD_CONTROLLER, STANDARD_ROBOT}
            nodes = kind.robot_nodes(controller) + tuple(n for n in nodes
                                                         if n not in robot_side)
        if view_port is not None:       # the view node, serving Foxglove on this port
            nodes = nodes + (VIEW,)
        self.view_port = view_port
        if workers < 0:
            raise ValueError(f'workers must be >= 0, got {workers}')
        self.workers, self.reset = workers, reset
        # a command to run a worker's nodes under, by worker name (e.g. 'worker1': ['ip',
        # 'netns', 'exec', 'lab']); '' = the graph's own nodes (memory, learner)
        self.launch_prefix = launch_prefix or {}
        self.task, self.mode = task, mode
        self.namespace = '/' + namespace.strip('/') if namespace.strip('/') else ''
        self.log_dir = Path(log_dir).resolve() if log_dir else default_log_dir()
        self.nodes_spec = nodes
        self.extra_params = extra_params or {}
        self.processes: list[NodeProcess] = []

    def params(self, name: str) -> dict:
        """The -p parameters of a node: the task for the simulator, the robot and the
        controller (none: their default, psl_task.DEFAULT_TASK), the mode for the simulator,
        the robot kind's (the controller's watchdog), the controller, clock and reset for the
        executor, the workers for the learner, the memory folder (``PSL_MEMORY_DIR``, if set)
        for the skill memory, the port for the view, then `extra_params`."""
        params = ({'task': self.task} if self.task and name in ('sim', 'robot', 'pd_controller')
                  else {})
        if name == 'sim':
            params['mode'] = self.mode
        if self.loop:               # the robot kind's settings of its nodes
            params.update(dict(self.kind.node_params).get(name, {}))
        if name == 'dmp_executor':
            params['controller'] = self.controller
            params['clock'] = self.kind.clock
            if self.reset:
                params['reset'] = self.reset          # teleport | drive ('' = the task's)
        if name == 'learner' and self.workers:
            params['workers'] = '[' + ','.join(self.worker_namespaces(relative=True)) + ']'
        if name == 'view' and self.view_port is not None:
            params['port'] = self.view_port
        if name == 'skill_memory' and os.environ.get('PSL_MEMORY_DIR'):
            params['memory_dir'] = os.environ['PSL_MEMORY_DIR']   # the memory files' folder
        params.update(self.extra_params.get(name, {}))
        return params

    def worker_namespaces(self, relative: bool = False) -> list[str]:
        """The namespaces the robot loop runs in: one per worker, or the graph's own."""
        if not self.workers:
            return [''] if relative else [self.namespace]
        names = [f'worker{k}' for k in range(self.workers)]
        return names if relative else [f'{self.namespace}/{n}' for n in names]

    def _plan(self) -> list[tuple[str, str, str, str, str]]:
        """(label, node name, package, executable, namespace) of every process."""
        plan = []
        for name, package, executable in self.nodes_spec:
            if self.workers and name in WORKER_NODES:
                for ns in self.worker_namespaces():
                    plan.append((f'{ns.rsplit("/", 1)[-1]}/{name}', name, package,
                                 executable, ns))
            else:
                plan.append((name, name, package, executable, self.namespace))
        return plan

    def start(self) -> list[NodeProcess]:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        remove_stale()          # shared memory that nodes which died (SIGKILL) left behind
        try:
            for label, name, package, executable, namespace in self._plan():
                cmd = [str(find_executable(package, executable)), '--ros-args']
                if namespace:
                    cmd += ['-r', f'__ns:={namespace}']
                for key, value in self.params(name).items():
                    cmd += ['-p', f'{key}:={value}']
                for topic, remapped in self.robot_topics.items():
                    cmd += ['-r', f'{topic}:={remapped}']
                worker = namespace if self.workers and name in WORKER_NODES else ''
                prefix = self.launch_prefix.get(worker.rsplit('/', 1)[-1], [])
                self.processes.append(self._spawn(label, list(prefix) + cmd, worker))
        except BaseException:
            self.stop()
            raise
        return self.processes

    def _spawn(self, label: str, cmd: list[str], worker: str, mode: str = 'wb') -> NodeProcess:
        log_path = self.log_dir / f'{label.replace("/", ".")}.log'
        with open(log_path, mode) as log:
            process = subprocess.Popen(
                cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                start_new_session=True)   # Ctrl-C reaches us only; we end them
        return NodeProcess(label, process, log_path, cmd, worker)

    def restart_worker(self, worker: str) -> list[NodeProcess]:
        """End the rest of a rollout worker's nodes (by PID) and start all of them again (a
        fresh loop: a simulator restarted alone would start its clock again under nodes that
        remember the old one). Their logs go on in the same files. Returns the new ones."""
        old = [p for p in self.processes if p.worker == worker]
        _end(old, timeout=3.0)
        remove_stale()          # what the dead node left in shared memory
        new = [self._spawn(p.name, p.cmd, worker, mode='ab') for p in old]
        self.processes = [p for p in self.processes if p.worker != worker] + new
        return new

    def drop_worker(self, worker: str) -> None:
        """End the rest of a rollout worker's nodes; the graph goes on without it."""
        old = [p for p in self.processes if p.worker == worker]
        _end(old, timeout=3.0)
        remove_stale()          # what the dead node left in shared memory
        self.processes = [p for p in self.processes if p.worker != worker]

    def dead(self) -> list[NodeProcess]:
        return [p for p in self.processes if p.process.poll() is not None]

    def describe_death(self, node: NodeProcess) -> str:
        code = node.process.returncode
        why = f'signal {signal.Signals(-code).name}' if code < 0 else f'exit code {code}'
        return f'{node.name} (pid {node.pid}) ended with {why}; its last output:\n{node.tail()}'

    def wait_ready(self, timeout: float = 30.0, stop=None) -> None:
        """Block until every worker's loop is connected (action server, reset service, every
        topic's endpoints) or `stop` (a threading.Event) is set; raise RuntimeError naming a
        dead node, or what is missing, otherwise."""
        from psl_ros.client import RosClient

        deadline = time.monotonic() + timeout
        names = {name for name, *_ in self.nodes_spec}
        loops = self.worker_namespaces() if 'dmp_executor' in names else []
        for namespace in loops:
            with RosClient(namespace) as client:
                while time.monotonic() < deadline and not (stop is not None
                                                           and stop.is_set()):
                    dead = self.dead()
                    if dead:
                        raise RuntimeError(self.describe_death(dead[0]))
                    if client.graph_ready(timeout=0.5):
                        break
                else:
                    if stop is not None and stop.is_set():
                        return
                    raise RuntimeError(
                        f'the graph was not ready within {timeout:.0f} s: missing '
                        f'{client.missing_endpoints()} in {namespace or "/"} (logs in '
                        f'{self.log_dir})')

    def view_url(self, timeout: float = 30.0) -> str:
        """The URL the graph's view node serves Foxglove on, once its log says so (it may
        have been given port 0). RuntimeError if the graph has no view node, it died, or it
        did not listen within `timeout` s."""
        from psl_ros.view_parameters import serving_url

        view = next((p for p in self.processes if p.name == VIEW[0]), None)
        if view is None:
            raise RuntimeError('this graph runs no view node (view_port)')
        deadline = time.monotonic() + timeout
        while True:
            url = serving_url(view.tail(200))
            if url:
                return url
            if view.process.poll() is not None:
                raise RuntimeError(self.describe_death(view))
            if time.monotonic() > deadline:
                raise RuntimeError(f'the view node did not listen within {timeout:.0f} s '
                                   f'(log: {view.log_path})')
            time.sleep(0.05)

    def stop(self, timeout: float = 5.0) -> None:
        """End every process this graph started, by PID."""
        _end(self.processes, timeout)

    def __enter__(self) -> 'Graph':
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def _end(processes: list[NodeProcess], timeout: float) -> None:
    """End processes by PID: SIGINT, then SIGTERM, then SIGKILL for those still alive."""
    for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, 2.0), (signal.SIGKILL, 2.0)):
        alive = [p for p in processes if p.process.poll() is None]
        if not alive:
            break
        for p in alive:
            try:
                os.kill(p.pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + wait
        for p in alive:
            try:
                p.process.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
