#!/usr/bin/env bash
# Measure everything the documentation's tables show, then refresh docs/data/ and docs/generated/ from it.
#
#   bash docs/measure.sh [OUT]      (OUT defaults to outputs/docs-measure; riskplan and its python on PATH,
#                                    e.g. in an activated venv)
#
# Run it on a quiet machine before a release: the benchmark, its scaling table, a full and a quick reproduction,
# the studies that docs/results.md shows beyond the reproduction, the figures of all of them, and the ray backend
# (bench/ray_backend.py; needs Ray: pip install -e '.[distributed]'). About 25 minutes on 2 cores, an estimate from
# the parts' own times, not timed as a whole (the ray backend's part took 11 of them on a loaded machine). A step
# whose result is already in OUT is not measured again (delete it to re-measure); the sweeps and
# bench/ray_backend.py skip their finished runs.
# Then: python docs/generate.py --check passes, and git diff shows what the new measurements changed.
set -euo pipefail
cd "$(dirname "$0")/.."
out=$(realpath -m "${1:-outputs/docs-measure}")
mkdir -p "$out"
fast=(train.eval_episodes=20000 train.bootstrap=200 train.paths=2)

load() { cut -d' ' -f1-3 /proc/loadavg > "$1.load"; }  # the load average as a measurement starts, for the docs
[ -f "$out/bench.json" ] || { load "$out/bench.json"; riskplan bench --json "$out/bench.json"; }
[ -f "$out/scaling.json" ] || { load "$out/scaling.json"
  riskplan bench --scaling --json "$out/scaling.json" --plot docs/figures/scaling.png; }
[ -f "$out/full/reproduce.json" ] || { load "$out/full"; riskplan reproduce --out "$out/full"; }
[ -f "$out/quick/reproduce.json" ] || { load "$out/quick"; riskplan reproduce --quick --out "$out/quick"; }

# Results beyond the reproduction (docs/results.md)
riskplan sweep experiment=paper_team team.order=combine_then_adapt,adapt_then_combine team.consensus_rounds=1,2,4,8 \
  seed=0 hydra.sweep.dir="$out/consensus_rounds"
riskplan sweep experiment=paper_team team.order=combine_then_adapt,adapt_then_combine,gradient_tracking \
  'seed=range(0,5)' "${fast[@]}" hydra.sweep.dir="$out/orders_line"
riskplan sweep experiment=paper_team team.order=combine_then_adapt,adapt_then_combine,gradient_tracking \
  team.robots=20 team.graph=random_geometric team.delay.max=2 team.drop=0.2 train.samples=300 \
  'seed=range(0,5)' "${fast[@]}" hydra.sweep.dir="$out/orders_rgg"
riskplan sweep experiment=paper_team team.robots=1 train.samples=6000 'seed=range(0,5)' "${fast[@]}" \
  hydra.sweep.dir="$out/orders_central"
riskplan sweep experiment=paper_single 'train.theta0=[0,0]' risk.schedule=none,linear,exponential 'seed=range(0,5)' \
  hydra.sweep.dir="$out/soft_risk_schedules"
riskplan sweep hydra/sweeper=optuna 'risk.beta=interval(0.05,1)' train.samples=2000 hydra.sweeper.n_trials=12 \
  hydra.sweeper.sampler.seed=0 train.eval_episodes=20000 train.bootstrap=200 hydra.sweep.dir="$out/optuna_coarse"
riskplan sweep hydra/sweeper=optuna 'risk.beta=interval(0.18,0.42)' hydra.sweeper.n_trials=12 \
  hydra.sweeper.sampler.seed=0 train.eval_episodes=20000 train.bootstrap=200 hydra.sweep.dir="$out/optuna_fine"
riskplan sweep experiment=paper_single policy.kind=tabular 'train.theta0=[0,0],[20,20]' \
  train.step_size.initial=0.1,1.0 train.iterations=200,1000 'seed=range(0,2)' "${fast[@]}" \
  hydra.sweep.dir="$out/tabular_steps"

# The ray backend (docs/results.md, Robots as Ray actors): its JSON files record the load average as each ends
[ -f "$out/ray/cluster.json" ] || python bench/ray_backend.py all --out "$out/ray"
for samples in 20000 200000; do
  [ -f "$out/ray/scaling_$samples.json" ] || python bench/ray_backend.py scaling --samples "$samples" --out "$out/ray"
done

# The figures: the reproduction's report, and reports of the studies that have figures of their own
rm -rf "$out/orders_report" "$out/soft_risk_report"
riskplan report "$out/orders_line" "$out/orders_rgg" --out "$out/orders_report" --format png
riskplan report "$out/soft_risk_schedules" --out "$out/soft_risk_report" --format png
for figure in fig1_paths fig2_cvar fig3_team fig4_consensus landscape risk_frontier \
  risk_measures richer_policies hetero_team faults; do
  cp "$out/full/report/$figure.png" docs/figures/
done
cp "$out/orders_report/consensus_orders.png" "$out/soft_risk_report/soft_risk.png" docs/figures/

studies=()
for name in consensus_rounds orders_line orders_rgg orders_central soft_risk_schedules optuna_coarse optuna_fine \
  tabular_steps; do
  studies+=(--study "$name=$out/$name")
done
python docs/generate.py --collect --reproduction "$out/full" --quick-reproduction "$out/quick" \
  --bench "$out/bench.json" --scaling "$out/scaling.json" "${studies[@]}" --ray "$out/ray"
python docs/generate.py --check
