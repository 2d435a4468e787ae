#!/usr/bin/env bash
# thirteenth session: 60 s rows, current tree then cc18fbe (.bg/old), same machine. usage: run13.sh TAG ROOT mesh:budget ...
set -u
tag=$1; root=$2; shift 2
summ() { python - "$1" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))["rows"][0]; t = r["timings"]; ph = t.get("dataset_phases", {})
print(f'{r["mesh"]} {r["budget_s"]:.0f}s call {r["call_s"]:.2f}s MRE {100*r["mre"]:.3f}% p99 {100*r["p99"]:.2f}% max {100*r["max"]:.1f}% heat {100*(r["heat_mre"] or 0):.3f}% '
      f'dataset {t["dataset_s"]:.2f}s (dist {ph.get("distances_s", -1):.2f} paths {ph.get("paths_s", -1):.2f}) steps {t.get("steps_s", -1):.2f}s '
      f'{r["steps"]} sources {r["sources"]} warn {bool(r["budget_warning"])}', flush=True)
PY
}
for spec in "$@"; do
  m=${spec%:*}; b=${spec#*:}
  d=$OUT/${tag}_${m}_${b}; mkdir -p $d
  date -u +"== $tag $m $b s %H:%M:%S"
  (cd $root && python benchmarks/time_to_accuracy.py --device cuda:0 --shared /tmp/bt --meshes $m --budgets $b --out $d --work /tmp/w_${tag}_${m}_${b} --path-refine 50 -q > $d/log.txt 2>&1)
  summ $d/time_to_accuracy.json || tail -20 $d/log.txt
done
