#!/bin/bash
# Reproduce the shipped DACN and depth networks of MOS-S1 and MOS-S2 and the README's DACN tables:
#
#     bash blender_addon/tools/reproduce_dacn.sh OUT
#
# 1. the factory data set: 170 seeded scenes at 480 x 640 (room 100, tabletop 40, street 30; seed 0);
# 2. DA2T pairs of every scene for each lens (8 perturbed lenses in a pool, noise, seed 0);
# 3. the equal-budget study (tiny-rb, 2000 iterations, batch 4 of 128^2, lr 5e-4, seed 0), its tables and
#    pictures in OUT/study/<lens>/ (table.md, eval.json, pictures/);
# 4. the depth networks (1500 iterations, seed 0);
# 5. the exports that ship in dcdi_core/models/weights/ (dacn-<lens>.npz: the study's `dacn` row,
#    depth-<lens>.npz), written to OUT/weights/.
# Every step resumes where a killed run stopped; run it again with the same OUT.
set -euo pipefail
OUT=${1:?usage: reproduce_dacn.sh OUT}
PY=${PYTHON:-.venv/bin/python}
mkdir -p "$OUT"
for spec in "room 100" "tabletop 40" "street 30"; do
  set -- $spec
  "$PY" -m blender_addon.factory --recipe "$1" --count "$2" --lens mos-s1 --out "$OUT/factory-$1" --seed 0
done
for lens in mos-s1 mos-s2; do
  for recipe in room tabletop street; do
    "$PY" -m dcdi_core dacn pairs "$OUT/factory-$recipe" --lens "$lens" -o "$OUT/pairs-$lens" --lens-pool 8 --seed 0
  done
done
"$PY" -m dcdi_core.experiments.dacn_study "$OUT/study" --pairs "mos-s1=$OUT/pairs-mos-s1" \
    --pairs "mos-s2=$OUT/pairs-mos-s2" --runs baseline,da2t,dacn --config tiny-rb --iters 2000 --lr 5e-4 --jobs 2
"$PY" -m dcdi_core.experiments.dacn_study "$OUT/study" --pairs "mos-s2=$OUT/pairs-mos-s2" \
    --runs baseline,da2t,dacn,dacn-diopter,scenes=34,scenes=68 --config tiny-rb --iters 2000 --lr 5e-4 --jobs 2
# the study scores the raw weights (--weights model, its default): at 2000 iterations the EMA (0.999) still holds
# 13.5 % of the initial network; the shipped files are the raw weights too
mkdir -p "$OUT/weights"
for lens in mos-s1 mos-s2; do
  "$PY" -m dcdi_core train depth --data "$OUT/pairs-$lens" --iters 1500 --seed 0 -o "$OUT/depth-$lens"
  "$PY" -m dcdi_core depth export "$OUT/depth-$lens" --weights model -o "$OUT/weights/depth-$lens.npz"
  "$PY" -m dcdi_core dacn export "$OUT/study/$lens/dacn" --weights model -o "$OUT/weights/dacn-$lens.npz"
done
echo "done: $OUT/weights (copy into dcdi_core/models/weights/), tables in $OUT/study/*/table.md"
