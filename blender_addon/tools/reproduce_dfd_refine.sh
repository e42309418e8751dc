#!/bin/bash
# Reproduce the learned refinement of the depth from blur (docs/depth.md) and its shipped files:
#
#     bash blender_addon/tools/reproduce_dfd_refine.sh OUT
#
# 1. factory frames at 480 x 640 (pip bpy): training scenes (seed 1: room, tabletop, street 24 each; and 72
#    dead-leaves frames, seed 5, so that it does not learn the rooms' depths alone), validation scenes
#    (seed 0: 8 each), held-out test scenes (seed 2: 6 each);
# 2. DA2T pairs at the paper's pitch (a crop of the 1280 x 1920 sensor at a seeded place, 12.2 um pixels,
#    sensor noise), the nominal lens (--perturb 0), for MOS-S1 and MOS-S2;
# 3. per lens, the study (blur alone, refined seeds 0 and 1, the same network without the evidence, the
#    constants; 1500 iterations) into OUT/study-<lens>/table.md, seed 0 exported to
#    OUT/weights/dfd-refine-<lens>.npz (what ships in dcdi_core/models/weights/).
# Every step resumes where a killed run stopped (the factory and the pairs do); run it again with the same OUT.
set -euo pipefail
OUT=${1:?usage: reproduce_dfd_refine.sh OUT}
PY=${PYTHON:-.venv/bin/python}
mkdir -p "$OUT/weights"
"$PY" -m blender_addon.factory --recipe leaves --count 72 --lens mos-s1 --out "$OUT/train-leaves" --seed 5
for spec in "train 1 24" "val 0 8" "test 2 6"; do
  set -- $spec
  for recipe in room tabletop street; do
    "$PY" -m blender_addon.factory --recipe "$recipe" --count "$3" --lens mos-s1 --out "$OUT/$1-$recipe" --seed "$2"
  done
done
for lens in mos-s1 mos-s2; do
  "$PY" -m dcdi_core dacn pairs "$OUT/train-leaves" --lens "$lens" -o "$OUT/pairs-$lens-train-leaves" --perturb 0 \
      --seed 3
  for spec in "train 3" "val 7" "test 11"; do
    set -- $spec
    for recipe in room tabletop street; do
      "$PY" -m dcdi_core dacn pairs "$OUT/$1-$recipe" --lens "$lens" -o "$OUT/pairs-$lens-$1" --perturb 0 --seed "$2"
    done
  done
  "$PY" -m dcdi_core.experiments.dfd_refine_study --lens "$lens" \
      --train "$OUT/pairs-$lens-train" "$OUT/pairs-$lens-train-leaves" \
      --val "$OUT/pairs-$lens-val" --test "$OUT/pairs-$lens-test" --seeds 0 1 --iters 1500 \
      --out "$OUT/study-$lens" --export "$OUT/weights/dfd-refine-$lens.npz"
done
