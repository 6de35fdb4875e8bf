# Source me: the one environment for psl (venv, workspace overlay, local-only discovery).
_psl_root="$(cd "$(dirname "${BASH_SOURCE[0]:-$0}")/.." && pwd)"
if [ ! -f "$_psl_root/install/setup.bash" ]; then
  echo "psl is not set up yet: run $_psl_root/scripts/setup (or make setup)" >&2
  return 1 2>/dev/null || exit 1
fi
# shellcheck disable=SC1091
source "$_psl_root/.venv/bin/activate"
export AMENT_PREFIX_PATH="$_psl_root/.venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
# colcon's setup scripts expect these to be set when run with 'set -u'
export COLCON_TRACE="${COLCON_TRACE:-}" AMENT_TRACE_SETUP_FILES="${AMENT_TRACE_SETUP_FILES:-}"
# shellcheck disable=SC1091
source "$_psl_root/install/setup.bash"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-42}"
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
# Fast DDS participant defaults (lease 4 s): a client notices a server that has gone in seconds
export FASTRTPS_DEFAULT_PROFILES_FILE="${FASTRTPS_DEFAULT_PROFILES_FILE:-$_psl_root/src/psl_ros/config/fastdds_profile.xml}"
export PSL_ROOT="$_psl_root"
# small matrices (hidden layers of ~100): one BLAS thread is faster and leaves the second core
# to the other nodes (batch ridge at N=100: 8 ms with threads, 0.3 ms without)
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}"
case ":$PATH:" in *":$_psl_root/scripts:"*) ;; *) export PATH="$_psl_root/scripts:$PATH" ;; esac
unset _psl_root
