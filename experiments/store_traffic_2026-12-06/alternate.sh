#!/bin/bash
# alternate.sh ROUNDS DEV: in a worktree DEV with stores_off.patch applied, SIMD_EXP 0 (the kernels as they are), 1 (no gradient-slot stores), 2 (no pair-record stores), 3 (neither); run from the checkout
DEV=$2

for i in $(seq $1); do
  for e in 0 1 2 3; do
    echo -n "exp$e "; SIMD_EXP=$e KEEP=1 PYTHONPATH="$DEV"/src python experiments/setup_simd_2026-12-06/harness.py time 9 800 600 200000
  done
done
