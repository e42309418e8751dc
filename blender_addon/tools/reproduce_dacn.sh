#!/bin/bash
# Reproduce the DACN study and the shipped DACNs of MOS-S1 and MOS-S2 (docs/correction.md):
#
#     bash blender_addon/tools/reproduce_dacn.sh OUT
#
# 1. factory frames at 480 x 640: training scenes (seed 1: leaves 200, room 36, tabletop 36) and held-out
#    scenes (seed 0: room, tabletop, street 12 each, leaves 40);
# 2. DA2T pairs at the paper's pitch (each frame a crop of the 1280 x 1920 sensor at a seeded place, 12.2 um
#    pixels), sensor noise, the nominal lens's deconvolution stored: training pairs through a pool of 4 lenses
#    perturbed within +-5 % and refocused (MOS-S2: room and tabletop twice, at two places), test pairs through
#    the nominal lens (seed 7);
# 3. the MOS-S2 study (rows baseline, da2t, refine, refine+mech, refine@2m; seeds 0 and 1; 4800 iterations
#    of batch 8 at 128^2, lr 5e-4, cosine): OUT/study/mos-s2/{data.md,table.md,curves.png,eval.json};
# 4. the longer budget (9600 iterations, otherwise the same recipe, seeds 0 and 1): MOS-S2 rows refine and
#    refine@2m, MOS-S1 refine: OUT/study-9600/<lens>/...; the baseline at 2 m against infinity (1600
#    iterations);
# 5. the exports that ship in dcdi_core/models/weights/ (dacn-<lens>.npz, the 9600-iteration refine row's
#    seed 0), written to OUT/weights/.
# Every step resumes where a killed run stopped; run it again with the same OUT.
set -euo pipefail
OUT=${1:?usage: reproduce_dacn.sh OUT}
PY=${PYTHON:-.venv/bin/python}
ITERS=${ITERS:-4800}
LONG=${LONG:-9600}
mkdir -p "$OUT"
for spec in "leaves 200" "room 36" "tabletop 36"; do
  set -- $spec
  "$PY" -m blender_addon.factory --recipe "$1" --count "$2" --lens mos-s1 --out "$OUT/train-$1" --seed 1
done
for spec in "room 12" "tabletop 12" "street 12" "leaves 40"; do
  set -- $spec
  "$PY" -m blender_addon.factory --recipe "$1" --count "$2" --lens mos-s1 --out "$OUT/test-$1" --seed 0
done
# training pairs of LENS into OUT/FOLDER: the leaves once, the rooms and desks VARIANTS times, a pool of 4 lenses
train_pairs() {
  local lens=$1 folder=$2 variants=$3; shift 3
  for recipe in leaves room tabletop; do
    local v=$variants
    if [ "$recipe" = leaves ]; then v=1; fi
    "$PY" -m dcdi_core dacn pairs "$OUT/train-$recipe" --lens "$lens" -o "$OUT/$folder" --lens-pool 4 \
        --variants "$v" "$@"
  done
}
train_pairs mos-s1 pairs-mos-s1-train 1
train_pairs mos-s2 pairs-mos-s2-train 2          # the study's lens: rooms and desks at two places each
for lens in mos-s1 mos-s2; do
  for recipe in room tabletop street leaves; do
    "$PY" -m dcdi_core dacn pairs "$OUT/test-$recipe" --lens "$lens" -o "$OUT/pairs-$lens-test" --perturb 0 --seed 7
  done
done
"$PY" -m dcdi_core.experiments.dacn_study "$OUT/study" --lens mos-s2 --train "$OUT/pairs-mos-s2-train" \
    --test "$OUT/pairs-mos-s2-test" --runs baseline,da2t,refine,refine+mech,refine@2m --seeds 0,1 \
    --iters "$ITERS" --lr 5e-4 --jobs 2
"$PY" -m dcdi_core.experiments.dacn_study "$OUT/study-$LONG" --lens mos-s2 --train "$OUT/pairs-mos-s2-train" \
    --test "$OUT/pairs-mos-s2-test" --runs refine,refine@2m --seeds 0,1 --iters "$LONG" --lr 5e-4 --jobs 2
"$PY" -m dcdi_core.experiments.dacn_study "$OUT/study-$LONG" --lens mos-s1 --train "$OUT/pairs-mos-s1-train" \
    --test "$OUT/pairs-mos-s1-test" --runs refine --seeds 0,1 --iters "$LONG" --lr 5e-4 --jobs 2
# the baseline's depth, 2 m against infinity (MOS-S2, seed 0, 1600 iterations, the same frames, lenses and places)
train_pairs mos-s2 pairs-mos-s2-train-inf 2 --baseline-depth inf
for spec in "2m pairs-mos-s2-train" "inf pairs-mos-s2-train-inf"; do
  set -- $spec
  "$PY" -m dcdi_core.experiments.dacn_study "$OUT/study-baseline-$1" --lens mos-s2 --train "$OUT/$2" \
      --test "$OUT/pairs-mos-s2-test" --runs baseline --seeds 0 --iters 1600 --lr 5e-4 --jobs 1
done
mkdir -p "$OUT/weights"
for lens in mos-s1 mos-s2; do
  "$PY" -m dcdi_core dacn export "$OUT/study-$LONG/$lens/refine-s0" --weights ema -o "$OUT/weights/dacn-$lens.npz"
done
echo "done: $OUT/weights (copy into dcdi_core/models/weights/), tables in $OUT/study*/*/table.md"
