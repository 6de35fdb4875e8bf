"""The command-line tests: as test/conftest.py, a ROS domain of this test session (set before
anything starts, inherited by every process a test starts) and discovery on this machine only,
so that the graphs the tests start do not meet other graphs."""
import os

os.environ['ROS_DOMAIN_ID'] = os.environ.get('PSL_TEST_DOMAIN_ID', str(1 + os.getpid() % 100))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
