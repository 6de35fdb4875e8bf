"""The whole suite: a ROS domain of this test run (set before anything starts, inherited by
every process a test starts), so that concurrent runs on one machine, and the workers of one
run (pytest-xdist), do not see each other's graphs; discovery on this machine only.

The domain: PSL_TEST_DOMAIN_ID if set, else one drawn from the run's process id, two apart
per run so that a run's second xdist worker takes the next one (1..100: the IDs whose DDS ports
fit on Linux)."""
import os

_worker = os.environ.get('PYTEST_XDIST_WORKER', 'gw0')
_index = int(_worker[2:]) if _worker[2:].isdigit() else 0
# an xdist worker's parent is the run's controller: every worker of a run draws from its pid
_run = os.getppid() if 'PYTEST_XDIST_WORKER' in os.environ else os.getpid()
_base = int(os.environ.get('PSL_TEST_DOMAIN_ID', 1 + 2 * (_run % 50)))
os.environ['ROS_DOMAIN_ID'] = str(_base + _index)
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
# the memory nodes the tests start keep their files under the system's temporary folder, where
# every tmp_path lies (a memory node refuses paths outside its memory_dir)
os.environ['PSL_MEMORY_DIR'] = __import__('tempfile').gettempdir()
