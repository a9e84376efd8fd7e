# Sourced by queue_worker.sh and queue_resume.sh: this machine's CPU type, and whether a queue line may run on it.
# Runs are bit-identical on one CPU type only (docs/RESULTS.md's 2026-11-30 07:55 line), so a run that pairs with runs
# made on given types names them on its queue line, and a worker on any other type leaves the line queued:
#
#   <name> [@<commit>] [cpu=<family>/<model>[,<family>/<model>...]] <python arguments...>
#
#   cpu_type                 # this machine's "<family>/<model>" (/proc/cpuinfo; SR_CPU_TYPE overrides it, for tests)
#   cpu_description          # "AMD EPYC, family 25 model 1, no AVX-512": what a run's start line names
#   line_cpu_types "<line>"  # the line's cpu= types as written ("6/167,6/207"), or nothing
#   line_runs_here "<line>"  # status 0 when the line names no type or names this machine's
cpu_type() {
  if [ -n "${SR_CPU_TYPE:-}" ]; then echo "$SR_CPU_TYPE"; return; fi
  awk -F': ' '/^cpu family/ {f=$2} /^model\t/ {n=$2} END {print f "/" n}' /proc/cpuinfo
}
cpu_description() {
  awk -F': ' '/^model name/ {m=$2} /^cpu family/ {f=$2} /^model\t/ {n=$2}
    /^flags/ {a=($0 ~ /avx512f/) ? "AVX-512" : "no AVX-512"} END {print m ", family " f " model " n ", " a}' /proc/cpuinfo
}
line_cpu_types() {
  local word
  # shellcheck disable=SC2086  (the line is split as the worker splits it, without globbing)
  set -f; set -- $1; set +f
  shift  # the name
  [[ "${1:-}" == @* ]] && shift
  word="${1:-}"
  [[ "$word" == cpu=* ]] && echo "${word#cpu=}"
  return 0
}
line_runs_here() {
  local types here
  types="$(line_cpu_types "$1")"
  [ -z "$types" ] && return 0
  here="$(cpu_type)"
  [[ ",$types," == *",$here,"* ]]
}
