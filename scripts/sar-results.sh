#!/usr/bin/env bash
# Reproduces docs/results: the beam-selection dataset and test flight, the decision
# tree with its top-K table, then the SAR mission with random, tree and oracle beam
# selection. Takes about half an hour on 2 CPU cores.
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$PWD/.venv/bin:$PATH"

caviar-core run blueprints/beam-dataset/config.toml --out runs/beam-dataset
caviar-core run blueprints/beam-dataset/test-flight.toml --out runs/beam-test-flight
python -m caviar_plugins.beam_selection.train_tree --train runs/beam-dataset --test runs/beam-test-flight \
    --out models/beam-tree.pkl --report-dir docs/results
python -m caviar_plugins.vision.train_detector --report docs/results/detector.json
python -m caviar_plugins.sar.results --tree models/beam-tree.pkl --out docs/results
