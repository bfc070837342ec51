#!/usr/bin/env bash
# Renders the paper's comparison figures into docs/figures/ with the offline commands
# (no server): Fig. 5 (light components of the Cornell box), Fig. 6 (translucency sweep),
# Fig. 7 (heterogeneous checkerboard block), Fig. 8 b–c (specular highlights on the bowls),
# simulated S against the dipole (the tall block, a bowl lit from inside),
# Fig. 12 (full model vs the two heuristics), the direct light per pixel against the
# all-per-vertex picture, and Figs. 1 and 10 (the two horses, frames of their animation,
# and the light only the full model has) where ../shared/data/horse.obj is.
# docs/figures/README.md says what each image shows.
#
#   bash scripts/figures.sh            # 3000 patches per scene, 400×300 images
#   PATCHES=6000 SIZE=640x480 bash scripts/figures.sh
#
# A few minutes on 2 cores: it builds the two binaries (release), precomputes its bundles
# into a temporary folder and renders the images.
set -euo pipefail

cd "$(dirname "$0")/.."
PATCHES="${PATCHES:-3000}"
SIZE="${SIZE:-400x300}"
WIDTH="${SIZE%x*}"
HEIGHT="${SIZE#*x}"
OUT=docs/figures
WORK="$(mktemp -d "${TMPDIR:-/tmp}/translux-figures.XXXXXX")"
trap 'rm -rf "$WORK"' EXIT

cargo build --release --quiet -p translux-precompute -p translux-server
BIN="${CARGO_TARGET_DIR:-target}/release"
mkdir -p "$OUT"

precompute() { # SCENE NAME
  echo "precompute $1 ($PATCHES patches)"
  "$BIN/translux-precompute" "$1" --out "$WORK/$2" --patches "$PATCHES" --quiet >/dev/null
}

render() { # BUNDLE OUT.png EXPOSURE REQUEST-JSON
  echo "render $2"
  printf '%s' "$4" >"$WORK/request.json"
  RUST_LOG=warn "$BIN/translux-server" render --bundle "$WORK/$1" --request "$WORK/request.json" \
    --out "$OUT/$2" --width "$WIDTH" --height "$HEIGHT" --exposure "$3" --tone filmic
}

# The Cornell box of builtin:cornell_paper with the tall block's marble 8× more translucent (the
# dipole's mean free path × 8): at a few thousand patches (4 cm each) real marble scatters
# within about one patch and looks opaque. Distances are stored to twice the truncation
# radius, so the sweep below can go up to scale 16 without new geometry work.
cat >"$WORK/cornell.json" <<'JSON'
{"name": "cornell8",
 "objects": [
  {"name": "floor", "mesh": {"shape": "quad", "size": [0.555, 0.555]},
   "material": {"type": "diffuse", "albedo": [0.725, 0.71, 0.68]}},
  {"name": "ceiling", "mesh": {"shape": "quad", "size": [0.555, 0.555]},
   "transform": {"rotate_deg": [180, 0, 0], "translate": [0, 0.555, 0]},
   "material": {"type": "diffuse", "albedo": [0.725, 0.71, 0.68]}},
  {"name": "back_wall", "mesh": {"shape": "quad", "size": [0.555, 0.555]},
   "transform": {"rotate_deg": [90, 0, 0], "translate": [0, 0.2775, -0.2775]},
   "material": {"type": "diffuse", "albedo": [0.725, 0.71, 0.68]}},
  {"name": "front_wall", "mesh": {"shape": "quad", "size": [0.555, 0.555]},
   "transform": {"rotate_deg": [-90, 0, 0], "translate": [0, 0.2775, 0.2775]},
   "material": {"type": "diffuse", "albedo": [0.725, 0.71, 0.68]}},
  {"name": "left_wall", "mesh": {"shape": "quad", "size": [0.555, 0.555]},
   "transform": {"rotate_deg": [0, 0, -90], "translate": [-0.2775, 0.2775, 0]},
   "material": {"type": "diffuse", "albedo": [0.63, 0.065, 0.05]}},
  {"name": "right_wall", "mesh": {"shape": "quad", "size": [0.555, 0.555]},
   "transform": {"rotate_deg": [0, 0, 90], "translate": [0.2775, 0.2775, 0]},
   "material": {"type": "diffuse", "albedo": [0.14, 0.45, 0.091]}},
  {"name": "short_box", "mesh": {"shape": "box", "size": [0.165, 0.165, 0.165]},
   "transform": {"rotate_deg": [0, -17, 0], "translate": [0.09, 0.0825, 0.07]},
   "material": {"type": "diffuse", "albedo": [0.75, 0.65, 0.15]}},
  {"name": "tall_block", "mesh": {"shape": "box", "size": [0.165, 0.33, 0.165]},
   "transform": {"rotate_deg": [0, 17, 0], "translate": [-0.09, 0.165, -0.08]},
   "material": {"type": "translucent",
                "profile": {"type": "dipole", "preset": "marble", "scale": 8}}}],
 "lights": [{"type": "point", "position": [0, 0.5, 0], "intensity": [0.8, 0.8, 0.8]}],
 "camera": {"position": [0, 0.2775, 1.3], "target": [0, 0.2775, 0], "fov_deg": 40}}
JSON
precompute "$WORK/cornell.json" cornell

# Simulated S against the dipole (issue 18): the same medium (σs′, σa in mm⁻¹, η = 1) as the
# validation suite's Mitsuba comparisons, once as a dipole profile and once as random walks
# inside the actual shape. The Cornell box's tall block, and a thin bowl lit from inside.
BLOCK_MEDIUM='"sigma_s_prime": [0.5, 0.45, 0.35], "sigma_a": [0.004, 0.008, 0.02], "eta": 1.0'
BOWL_MEDIUM='"sigma_s_prime": [1.0, 0.8, 0.6], "sigma_a": [0.005, 0.01, 0.02], "eta": 1.0'
for kind in dipole simulated; do
  if [ "$kind" = dipole ]; then
    block="{\"type\": \"translucent\", \"profile\": {\"type\": \"dipole\", $BLOCK_MEDIUM}}"
    bowl="{\"type\": \"translucent\", \"profile\": {\"type\": \"dipole\", $BOWL_MEDIUM}}"
  else
    block="{\"type\": \"simulated\", $BLOCK_MEDIUM}"
    bowl="{\"type\": \"simulated\", $BOWL_MEDIUM}"
  fi
  python3 - "$WORK/cornell.json" "$block" >"$WORK/block_$kind.json" <<'PY'
import json, sys
scene = json.load(open(sys.argv[1]))
for o in scene["objects"]:
    if o["name"] == "tall_block":
        o["material"] = json.loads(sys.argv[2])
scene["name"] = "block"
print(json.dumps(scene))
PY
  cat >"$WORK/bowl_$kind.json" <<JSON
{"name": "bowl",
 "objects": [
  {"name": "table", "mesh": {"shape": "quad", "size": [0.5, 0.5]},
   "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
  {"name": "bowl", "mesh": {"shape": "bowl", "radius": 0.05, "thickness": 0.004},
   "material": $bowl}],
 "lights": [{"type": "point", "position": [0, 0.035, 0], "intensity": [0.02, 0.02, 0.02]}],
 "camera": {"position": [0, 0.11, 0.2], "target": [0, 0.03, 0], "fov_deg": 45}}
JSON
  precompute "$WORK/block_$kind.json" "block_$kind"
  precompute "$WORK/bowl_$kind.json" "bowl_$kind"
done
precompute builtin:cornell_checker checker
precompute builtin:cornell cornell_glow
precompute builtin:cornell_paper cornell_paper
precompute builtin:bowls bowls

# Fig. 5: direct, inter-reflection only, subsurface only, full (the paper's order). The
# components with inter-reflection are 3–4× brighter: they are shown 1.5 EV darker.
EV=-1
for c in direct subsurface_only; do
  render cornell "fig5_$c.png" 0.5 "{\"components\":\"$c\"}"
done
for c in interreflection_only full; do
  render cornell "fig5_$c.png" "$EV" "{\"components\":\"$c\"}"
done

# Fig. 6: the block from less to more translucent (marble's mean free path × 1, 4, 16; S
# rebuilt from the stored distances, no geometry work).
for s in 1 4 16; do
  render cornell "fig6_scale_$s.png" "$EV" \
    "{\"materials\":{\"tall_block\":{\"type\":\"translucent\",\"profile\":{\"type\":\"dipole\",\"preset\":\"marble\",\"scale\":$s}}}}"
done

# Fig. 7: the tall block a checkerboard of marble and an orange medium.
render checker fig7_checker.png "$EV" '{}'

# The Cornell box as the viewer shows it (builtin:cornell: the block's marble ×16, a spot
# hidden behind it, the ceiling lamp dimmed) beside the paper's (builtin:cornell_paper, real
# marble, the ceiling lamp alone), each under its own lights, from the same camera.
render cornell_glow cornell_glow.png -2.5 '{}'
render cornell_paper cornell_paper.png -2 '{}'

# Fig. 12: the bowls lit from inside: full model, heuristic A, heuristic B.
for c in full heuristic_a heuristic_b; do
  render bowls "fig12_$c.png" 2 "{\"components\":\"$c\"}"
done

# Fig. 8 b–c: the bowls and the blob with a glossy coat (GGX, roughness 0.25, eta from each
# medium) and a lamp above the front added to the lights inside the bowls, against the same
# picture without the specular pass.
GLOSSY='{"materials":{'
for b in red_bowl:0.003,0.12,0.15:2.2,2.0,1.9 green_bowl:0.14,0.004,0.11:2.0,2.2,2.0 \
  blue_bowl:0.16,0.09,0.003:1.9,2.0,2.2; do
  IFS=: read -r name sa ss <<<"$b"
  GLOSSY+="\"$name\":{\"type\":\"translucent\",\"profile\":{\"type\":\"dipole\",\"sigma_a\":[$sa],\"sigma_s_prime\":[$ss],\"eta\":1.3},\"specular\":{\"roughness\":0.25}},"
done
GLOSSY+='"blob":{"type":"translucent","profile":{"type":"dipole","preset":"skimmilk"},"specular":{"roughness":0.25}}},'
GLOSSY+='"lights":['
for at in -0.22,0.05,-0.06 0,0.05,-0.13 0.22,0.05,-0.06; do
  GLOSSY+="{\"type\":\"point\",\"position\":[$at],\"intensity\":[0.05,0.05,0.05]},"
done
GLOSSY+='{"type":"point","position":[0.1,0.45,0.45],"intensity":[0.4,0.4,0.4]}]'
render bowls fig8_specular.png 0 "$GLOSSY}"
render bowls fig8_no_specular.png 0 "$GLOSSY,\"specular\":false}"

# Simulated S against the dipole: the tall block under the box's light, and the bowl lit by
# a lamp inside it (its outside glows only by light that crossed the wall).
for kind in dipole simulated; do
  render "block_$kind" "sim_block_$kind.png" "$EV" '{}'
  render "bowl_$kind" "sim_bowl_$kind.png" -2.5 '{}'
done

# The direct light per pixel (renders' default) against the same light at the vertices.
render cornell crisp_pixel.png "$EV" '{"direct_at":"pixel"}'
render cornell crisp_vertex.png "$EV" '{"direct_at":"vertex"}'

# Fig. 8 c: the same glossy bowls under the sky alone (environment light, its specular
# reflection included).
render bowls fig8_environment.png 0 \
  "${GLOSSY%%\"lights\"*}\"lights\":[{\"type\":\"environment\",\"map\":\"builtin:sky\",\"scale\":1}]}"

# Figs. 1 and 10: the two horses of examples/scenes/horses-gallop.json (48 frames; F and S
# per frame, as the paper's gallop) with a glossy coat. (b)/(d): the light that only the
# full model has — full minus subsurface scattering alone, the paper's "missing light
# transport component" — from two linear EXR renders (tests/examples/exrdiff.rs).
HORSES=examples/scenes/horses-gallop.json
if [ -f ../shared/data/horse.obj ]; then
  cargo build --release --quiet -p translux-tests --example exrdiff
  echo "precompute $HORSES (48 frames, $PATCHES patches each)"
  "$BIN/translux-precompute" "$HORSES" --out "$WORK/horses" --patches "$PATCHES" --quiet >/dev/null
  COAT='"specular":{"roughness":0.3}'
  HMAT="\"materials\":{\"horse_marble\":{\"type\":\"translucent\",\"profile\":{\"type\":\"dipole\",\"preset\":\"marble\"},$COAT},\"horse_milk\":{\"type\":\"translucent\",\"profile\":{\"type\":\"dipole\",\"preset\":\"skimmilk\"},$COAT}}"
  horses() { # OUT-STEM FRAME EV EXTRA-JSON
    render horses "$1.png" "$3" "{\"frame\":$2,$HMAT$4}"
    for c in full subsurface_only; do
      printf '%s' "{\"frame\":$2,\"components\":\"$c\",$HMAT$4}" >"$WORK/request.json"
      RUST_LOG=warn "$BIN/translux-server" render --bundle "$WORK/horses" \
        --request "$WORK/request.json" --out "$WORK/$c.exr" --width "$WIDTH" --height "$HEIGHT"
    done
    echo "render $1_missing.png"
    "$BIN/examples/exrdiff" "$WORK/full.exr" "$WORK/subsurface_only.exr" "$OUT/$1_missing.png" \
      "$(awk "BEGIN{print $3 + 1.5}")" filmic
  }
  horses fig1_horses 20 0 ''
  horses fig1_horses_relit 20 0 \
    ',"camera":{"position":[1.5,0.45,1.3],"target":[0.05,0.12,0],"fov_deg":40},"lights":[{"type":"spot","position":[-0.9,0.9,0.8],"direction":[0.9,-0.8,-0.8],"intensity":[4,3.6,3],"inner_deg":20,"outer_deg":35}]'
  horses fig10_frame08 8 0 ''
  horses fig10_frame36 36 0 ''
else
  echo "skipping Figs. 1 and 10: ../shared/data/horse.obj is not there"
fi

echo "wrote $(ls "$OUT"/*.png | wc -l) images to $OUT"
