#!/bin/bash
# usage: setrun.sh TAG MESH BUDGET [KEY=VALUE...]
tag=$1; m=$2; b=$3; shift 3
sets=""; for kv in "$@"; do sets="$sets --set $kv"; done
python /work/main/benchmarks/time_to_accuracy.py --device cpu --meshes $m --budgets $b --out /tmp/s14/cpu/${tag}_${m}_${b} --work /tmp/s14/cpu/${tag}_${m}_${b}/work --path-refine 50 -q $sets > /tmp/s14/cpu/${tag}_${m}_${b}.log 2>&1
