#!/usr/bin/env bash
# The two passes of `make test`, side by side (usage: tests/passes.sh VENV_BIN "and not slow"|"").
#
# The serial pass (real time: daemons, sockets, the network lab; tests/conftest.py marks it)
# runs at normal priority, one test at a time. The parallel pass (virtual clock, no sockets,
# on every core with pytest-xdist) runs beside it under SCHED_IDLE: the kernel gives it only
# the CPU the serial tests leave idle (a daemon run at speed 2 uses about one of the two
# cores), so it cannot change their timing, and the two passes together take little more
# than the serial one. `nice -n 19` stands in where SCHED_IDLE is refused. The parallel
# pass's output follows the serial pass's; the exit status fails if either pass failed.
set -uo pipefail
bin=$1
not_slow=${2:-}
log=$(mktemp)
if chrt --idle 0 true 2>/dev/null; then idle=(chrt --idle 0); else idle=(nice -n 19); fi
"${idle[@]}" "$bin/pytest" -q -n auto -m "not serial $not_slow" >"$log" 2>&1 &
pure=$!
# a background job of a script ignores SIGINT: end it with us
trap 'kill -TERM "$pure" 2>/dev/null; rm -f "$log"' EXIT
trap 'exit 130' INT TERM
"$bin/pytest" -q -m "serial $not_slow"
serial=$?
wait "$pure"
parallel=$?
echo "--- the parallel pass (it ran beside the serial pass, at idle priority; exit $parallel):"
cat "$log"
exit $((serial != 0 || parallel != 0))
