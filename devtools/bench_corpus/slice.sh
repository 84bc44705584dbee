#!/bin/sh
# The autotemp bench's corpus (tests/data/gcode/corpus/, README.md there):
# each model made with openscad and sliced with Debian's PrusaSlicer 2.5.0.
#   apt-get install -y prusa-slicer openscad
#   sh devtools/bench_corpus/slice.sh OUT_DIR
# writes OUT_DIR/NAME.gcode.gz (the slicer's configuration block left out).
set -eu
here=$(cd "$(dirname "$0")" && pwd)
out=${1:?usage: slice.sh OUT_DIR}
mkdir -p "$out"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

common="--center 110,110 --bed-shape 0x0,220x0,220x220,0x220 --skirts 1 --filament-diameter 1.75"
klipper_user="--gcode-flavor marlin2 --perimeter-speed 120 --external-perimeter-speed 80 \
 --infill-speed 250 --solid-infill-speed 200 --top-solid-infill-speed 100 --gap-fill-speed 100 \
 --travel-speed 250 --first-layer-speed 40"
pla="--temperature 210 --first-layer-temperature 215 --filament-type PLA"
petg="--temperature 240 --first-layer-temperature 240 --filament-type PETG"
relative="--use-relative-e-distances --layer-gcode G92\ E0"
print_start='--start-gcode PRINT_START\ EXTRUDER={first_layer_temperature[0]}\ BED={first_layer_bed_temperature[0]}'

slice() { # NAME MODEL OPTIONS...
  name=$1 model=$2; shift 2
  openscad -o "$work/$model.stl" "$here/$model.scad" 2>/dev/null
  eval prusa-slicer --export-gcode $common "$@" -o "$work/$name.gcode" "$work/$model.stl" >/dev/null 2>&1
  sed '/^; prusaslicer_config = begin/,$d' "$work/$name.gcode" | gzip -9n > "$out/$name.gcode.gz"
  echo "$name: $(zcat "$out/$name.gcode.gz" | wc -l) lines"
}

slice small_parts_fwretract_petg small_parts $petg --gcode-flavor marlin2 --use-firmware-retraction
slice twisted_gear_relative_pla twisted_gear $pla $klipper_user $relative "$print_start" \
  --gcode-resolution 0.002 --fill-density 15%
slice text_absolute_pla text $pla --retract-length 0.8 --infill-speed 120 --perimeter-speed 60
slice thin_walls_fwretract_petg thin_walls $petg --gcode-flavor marlin2 --use-firmware-retraction \
  $relative --thin-walls --perimeter-speed 80 --infill-speed 150
slice vase_spiral_pla vase $pla --spiral-vase --perimeters 1 --top-solid-layers 0 \
  --bottom-solid-layers 3 --fill-density 0% --perimeter-speed 70 --external-perimeter-speed 70
slice bracket_0.6mm_petg bracket $petg $klipper_user $relative --nozzle-diameter 0.6 \
  --layer-height 0.3 --first-layer-height 0.3 --retract-length 1 --infill-speed 150 --solid-infill-speed 120
slice spur_gear_absolute_pla spur_gear $pla $klipper_user --retract-length 0.8 --wipe
slice gyroid_cube_pla gyroid_cube $pla $klipper_user --fill-pattern gyroid --fill-density 25% \
  --start-gcode 'START_PRINT\ EXTRUDER_TEMP={first_layer_temperature[0]}\ BED_TEMP={first_layer_bed_temperature[0]}'
