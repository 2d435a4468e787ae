#!/usr/bin/env bash
# sixteenth session: rows with optional --set changes, the compile plan printed. usage: run16.sh TAG "SETS" mesh:budget ...
set -u
tag=$1; sets=$2; shift 2
extra=""; for kv in $sets; do extra="$extra --set $kv"; done
summ() { python - "$1" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))["rows"][0]; t = r["timings"]
print(f'{r["mesh"]} {r["budget_s"]:.0f}s call {r["call_s"]:.2f}s MRE {100*r["mre"]:.3f}% p99 {100*r["p99"]:.2f}% max {100*r["max"]:.1f}% heat {100*(r["heat_mre"] or 0):.3f}% '
      f'val {100*(r.get("validation_mre") or 0):.3f}% sdf {r.get("sdf_l1")} ch {r.get("chamfer_refined")} dataset {t["dataset_s"]:.2f}s steps {t.get("steps_s", -1):.2f}s {r["steps"]} src {r["sources"]["distance"]} warn {bool(r["budget_warning"])} compile {t.get("compile")}', flush=True)
PY
}
for spec in "$@"; do
  m=${spec%:*}; b=${spec#*:}
  d=$OUT/${tag}_${m}_${b}; mkdir -p $d
  date -u +"== $tag $m $b s %H:%M:%S [$sets]"
  python benchmarks/time_to_accuracy.py --device cuda:0 --shared /tmp/bt --meshes $m --budgets $b --out $d --work /tmp/w_${tag}_${m}_${b} --path-refine 50 -q $extra > $d/log.txt 2>&1
  summ $d/time_to_accuracy.json || tail -20 $d/log.txt
done
