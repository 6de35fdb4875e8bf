# Source me: the one environment for psl (venv, workspace overlay, local-only discovery).
_psl_root="$(cd "$(dirname "${BASH_SOURCE[0]:-$0}")/.." && pwd)"
if [ ! -f "$_psl_root/install/setup.bash" ]; then
  echo "psl is not set up yet: run $_psl_root/scripts/setup (or make setup)" >&2
  return 1 2>/dev/null || exit 1
fi
# colcon's setup scripts expect these to be set when run with 'set -u'
export COLCON_TRACE="${COLCON_TRACE:-}" AMENT_TRACE_SETUP_FILES="${AMENT_TRACE_SETUP_FILES:-}"
# psl set up with the control_msgs of a ROS installation (scripts/setup): that installation
# stays after the venv when sourced already, as at set-up; else it is sourced here, first
_psl_cm="$(cat "$_psl_root/.venv/.psl/control_msgs" 2>/dev/null || true)"
if [ -n "$_psl_cm" ]; then
  case ":${AMENT_PREFIX_PATH:-}:" in
    *":$_psl_cm:"*) ;;
    *) if [ -f "$_psl_cm/setup.bash" ]; then
         # shellcheck disable=SC1091
         source "$_psl_cm/setup.bash"
       else
         echo "psl was set up with control_msgs from $_psl_cm, which has gone: run scripts/setup" >&2
       fi ;;
  esac
fi
unset _psl_cm
# shellcheck disable=SC1091
source "$_psl_root/.venv/bin/activate"
export AMENT_PREFIX_PATH="$_psl_root/.venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
# shellcheck disable=SC1091
source "$_psl_root/install/setup.bash"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-42}"
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
# Fast DDS participant defaults (lease 4 s): a client notices a server that has gone in seconds
export FASTRTPS_DEFAULT_PROFILES_FILE="${FASTRTPS_DEFAULT_PROFILES_FILE:-$_psl_root/src/psl_ros/config/fastdds_profile.xml}"
export PSL_ROOT="$_psl_root"
# Ray (psl bench sweeps): every node and driver of a cluster authenticates with the token in
# ~/.ray/auth_token (Ray reads this when it is imported)
export RAY_AUTH_MODE="${RAY_AUTH_MODE:-token}"
# small matrices (hidden layers of ~100): one BLAS thread is faster and leaves the second core
# to the other nodes (batch ridge at N=100: 8 ms with threads, 0.3 ms without)
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}"
case ":$PATH:" in *":$_psl_root/scripts:"*) ;; *) export PATH="$_psl_root/scripts:$PATH" ;; esac
unset _psl_root
