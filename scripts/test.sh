#!/usr/bin/env bash
# `make test`: the multi-process graph tests and all the others as two pytest sessions at
# once (2 cores: the graph tests wait on DDS and on plant time, the others compute), each in a
# ROS domain of its own (the graph session also runs the modules marked beside_graphs, after
# the graphs, so that both end about together). The graph session identifies the model banks
# in the background; the other's bank fixtures wait for them. Both at the same priority:
# niced, the other session got a tenth of a core beside a graph's node processes and finished
# three minutes after the graph session, alone on one core. Extra arguments go to both
# sessions. Exit status: non-zero if either session failed; the graph session's output follows
# the other's.
set -uo pipefail
# one BLAS thread per process: two sessions and the graphs' node processes share 2 cores, and
# OpenBLAS's spinning worker threads would take the CPU the other processes need
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}" OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="$ROOT/.venv/bin/python"
base="${ROS_DOMAIN_ID:-$(( ($$ % 100) + 100 ))}"
mkdir -p "$ROOT/build"
log="$ROOT/build/test-graph.log"
cd "$ROOT"
ROS_DOMAIN_ID=$(( (base + 101) % 232 )) "$PY" -m pytest tests -m "graph or beside_graphs" "$@" \
    > "$log" 2>&1 &
graph=$!
trap 'kill -INT $graph 2>/dev/null; wait $graph' INT TERM
ROS_DOMAIN_ID=$base FDI_ROS_TEST_BANK_BUILDER=0 "$PY" -m pytest tests \
    -m "not graph and not beside_graphs" "$@"
rest=$?
wait $graph
rc=$?
echo "================================ graph tests ($log)"
cat "$log"
echo "[test] other tests: exit $rest; graph tests: exit $rc"
[ "$rest" -eq 0 ] && [ "$rc" -eq 0 ]
