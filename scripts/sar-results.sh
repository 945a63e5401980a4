#!/usr/bin/env bash
# Reproduces the SAR result sets (docs/paper-protocol.md):
#
#   docs/results/paper-protocol/{topk,mission,degradation}.{md,json,png}  (protocol = "paper")
#   docs/results/physical/{topk,mission,degradation}.{md,json,png}        (protocol = "physical")
#
# Paper protocol: the six 2023 training flights and the SAR test flight with the 2023
# link, the tree (and the k-NN gain selector) with the 2023 top-K protocol, the mission
# with random, tree, oracle and k-NN, and the degradation table. About 30 min on 2 CPU
# cores. Completed runs under runs/ are reused; delete them to measure afresh.
#
# Physical protocol: the top-K and mission tables are reformatted from the measured
# results in docs/results (mission.json, topk.json); FULL_PHYSICAL=1 re-measures them
# first (several hours on 2 cores). The degradation table is measured.
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$PWD/.venv/bin:$PATH"

completed() { [ -f "$1/run.json" ] && grep -q '"status": "completed"' "$1/run.json"; }

# --- paper protocol -----------------------------------------------------------------------
MISSION_NOTE="Measured by \`python -m caviar_plugins.tools.results.sar\` on blueprints/sar-paper/config.toml \
(protocol = paper; configs in configs/). Mission time = 8.5 s takeoff offset (an estimate, \`clock_offset_s\`) \
+ the flight to leaving waypoint 4 (208.3 m, 45 s without hovers) + hovers of (ceil(S/0.5) + 1) x 0.5 s, \
S = 320 Mbit / R of the previous step. A person is rescued once (the 2023 code counted detection events). \
Random: one run of the 2023 draw sequence (default_rng(1)); it is dominated by 1/R tails. \
k-NN gain + previous sweep, previous beam and sweep forest: the better selectors of topk.md in the loop. Runs stop at \
2400 steps (1200 s); a run stopped there has a lower bound ('>'). 'At a person': rescues within 5 m of a placed \
person (the others are false detections on degraded frames). Sionna RT 2.x, 1e5 rays per source (1e6 in 2023)."
train=()
for i in 0 1 2 3 4 5; do
    out=runs/paper-dataset-$i
    completed "$out" || { rm -rf "$out"; caviar-core run blueprints/beam-dataset/paper.toml --quiet --out "$out" \
        --set "modules.uav.params.waypoints=\"paper_train_path$i.csv\""; }
    train+=("$out")
done
completed runs/paper-test-flight || { rm -rf runs/paper-test-flight;
    caviar-core run blueprints/beam-dataset/paper-test-flight.toml --quiet --out runs/paper-test-flight; }
python -m caviar_plugins.tools.baselines.paper_topk --train "${train[@]}" --test runs/paper-test-flight \
    --out docs/results/paper-protocol --model models/paper-beam-tree.pkl --knn-model models/paper-beam-knn.pkl \
    --knn-previous-model models/paper-beam-knn-previous.pkl --sweep-model models/paper-beam-sweep-forest.pkl
python -m caviar_plugins.tools.results.sar --config blueprints/sar-paper/config.toml --reuse --runs runs/paper \
    --tree models/paper-beam-tree.pkl --knn models/paper-beam-knn-previous.pkl --set episode.steps=2400 \
    --methods random tree oracle knn previous sweep \
    --out docs/results/paper-protocol --note "$MISSION_NOTE"
python -m caviar_plugins.tools.results.degradation --protocol paper --out docs/results/paper-protocol \
    --runs runs/paper/sar-random runs/paper/sar-tree runs/paper/sar-oracle runs/paper/sar-knn runs/paper/sar-previous runs/paper/sar-sweep

# --- physical protocol --------------------------------------------------------------------
if [ "${FULL_PHYSICAL:-0}" = 1 ]; then
    caviar-core run blueprints/beam-dataset/config.toml --out runs/beam-dataset
    caviar-core run blueprints/beam-dataset/test-flight.toml --out runs/beam-test-flight
    python -m caviar_plugins.tools.training.train_tree --train runs/beam-dataset --test runs/beam-test-flight \
        --out models/beam-tree.pkl --report-dir docs/results
    python -m caviar_plugins.tools.training.train_detector --report docs/results/detector.json
    python -m caviar_plugins.tools.results.sar --tree models/beam-tree.pkl --out docs/results
fi
python -m caviar_plugins.tools.results.physical --src docs/results --out docs/results/physical
python -m caviar_plugins.tools.results.degradation --protocol physical --out docs/results/physical
