#!/bin/bash
# Reproduce the shipped depth networks (dcdi_core/models/weights/depth-mos-s1.npz, depth-mos-s2.npz):
#
#     bash blender_addon/tools/reproduce_depth.sh OUT
#
# They learned the former DA2T pairs: 170 factory scenes at 480 x 640 (room 100, tabletop 40, street 30; seed 0),
# each frame spanning the sensor (35.2 um), lenses perturbed within +-10 % without refocus (a pool of 8), noise;
# 1500 iterations, seed 0. Neither is recorded better than a constant depth, so `dcdi dof` does not run them
# unasked (docs/pipeline.md). Every step resumes where a killed run stopped; run it again with the same OUT.
set -euo pipefail
OUT=${1:?usage: reproduce_depth.sh OUT}
PY=${PYTHON:-.venv/bin/python}
mkdir -p "$OUT/weights"
for spec in "room 100" "tabletop 40" "street 30"; do
  set -- $spec
  "$PY" -m blender_addon.factory --recipe "$1" --count "$2" --lens mos-s1 --out "$OUT/factory-$1" --seed 0
done
for lens in mos-s1 mos-s2; do
  for recipe in room tabletop street; do
    "$PY" -m dcdi_core dacn pairs "$OUT/factory-$recipe" --lens "$lens" -o "$OUT/pairs-$lens" --lens-pool 8 \
        --seed 0 --perturb 0.1 --no-refocus --full-sensor --placement centre --no-deconvolved
  done
  "$PY" -m dcdi_core depth train --data "$OUT/pairs-$lens" --iters 1500 --seed 0 -o "$OUT/depth-$lens"
  "$PY" -m dcdi_core depth export "$OUT/depth-$lens" --weights model -o "$OUT/weights/depth-$lens.npz"
done
echo "done: $OUT/weights (copy into dcdi_core/models/weights/)"
