#!/bin/bash
# alt2.sh ROUNDS BASE_SRC NEW_SRC: harness.py's timing of 800x600 / 200k through "auto" (each
# render after a numba one, cProfile's split), the two trees alternated in ABBA order.
here=$(dirname "$0")
for i in $(seq "$1"); do
  for w in base new new base; do
    if [ $w = base ]; then p=$2; else p=$3; fi
    echo -n "$w "; KEEP=1 PYTHONPATH=$p python "$here/harness.py" time 9 800 600 200000
  done
done
