#!/usr/bin/env bash
# Evaluate a generalist policy where it has to hold, zero-shot, on unseen targets, static and
# dynamic (the beating aorta), beside the centerline follower:
#   real/        the five held-out real aortas (cgail_sim.anatomy_spec.REAL_HELD_OUT), 15 trials
#                each on target set 1, pooled, with a per-aorta table and failure pictures;
#   population/  the first 20 held-out population anatomies, 15 trials each;
#   builtins/    default and elongated, 30 trials each on target set 1.
# Each directory holds report.md, results.json and the pictures; the summary is printed last
# and written to OUT/summary.md.
#
#   bash scripts/evaluate_generalist.sh POLICY.onnx [OUT]     # default OUT: <policy dir>/eval
set -euo pipefail
WS="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$WS"
if [ $# -lt 1 ] || [ ! -f "$1" ]; then
    echo "evaluate_generalist: error: expected an exported policy POLICY.onnx as the first argument, found '${1:-}'" >&2
    exit 2
fi
POLICY="$1"
OUT="${2:-$(dirname "$POLICY")/eval}"
mkdir -p "$OUT"
common=(--policy "generalist=$POLICY" --baselines centerline --modes static dynamic)
t0=$(date +%s)
echo "[evaluate-generalist] held-out real aortas"
scripts/ws cgail evaluate "${common[@]}" --anatomy avt-D4 avt-D10 avt-D13 avt-D15 avt-D18 \
    --trials 15 --scenario-seed 1 --out "$OUT/real" > "$OUT/real.log"
echo "[evaluate-generalist] held-out population anatomies"
scripts/ws cgail evaluate "${common[@]}" --population 20 --trials 15 \
    --out "$OUT/population" > "$OUT/population.log"
echo "[evaluate-generalist] built-in anatomies"
scripts/ws cgail evaluate "${common[@]}" --anatomy default elongated --trials 30 \
    --scenario-seed 1 --out "$OUT/builtins" > "$OUT/builtins.log"
scripts/ws python - "$OUT" <<'EOF'
import json
import sys
from pathlib import Path

out = Path(sys.argv[1])
lines = ['| where | mode | method | success [95% Wilson CI] | per anatomy |', '|---|---|---|---|---|']
for where in ('real', 'population', 'builtins'):
    data = json.loads((out / where / 'results.json').read_text())
    for mode, methods in data['modes'].items():
        for name, entry in methods.items():
            s = entry['summary']
            k = sum(t['success'] for t in entry['trials'])
            per = data.get('per_anatomy_success', {}).get(mode, {}).get(name, {})
            per_s = ', '.join(f'{a.replace("population-", "p")} {100 * v:.0f}' for a, v in per.items())
            lines.append(f'| {where} | {mode} | {name} | {100 * s["success_rate"]:.0f}% ({k}/{s["n"]}; '
                         f'{100 * s["success_ci"][0]:.0f}-{100 * s["success_ci"][1]:.0f}) | '
                         f'{per_s if where != "population" else ""} |')
text = '\n'.join(lines)
(out / 'summary.md').write_text(text + '\n')
print(text)
EOF
echo "[evaluate-generalist] $OUT/summary.md ($(( $(date +%s) - t0 )) s)"
