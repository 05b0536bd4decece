#!/usr/bin/env bash
# The main job on built-in defaults: photo -> views -> avatar -> USD animation + preview video.
# Run from the repository root after installing (README's first command does both).
set -euo pipefail
PY="${PY:-.venv/bin/python}"
DLA="${DLA:-.venv/bin/dla}"
OUT="${1:-out/demo}"
mkdir -p "$OUT"
PHOTO="$("$PY" -c "from dlacli.paths import sample_photo; print(sample_photo())")"
step() { local s=$SECONDS; echo "$1" >&2; shift; "$@"; echo "  ($((SECONDS - s)) s)" >&2; }

# No --keypoints: the person's keypoints are detected (MediaPipe Pose), as for a user's own photo.
step "1/3 dream: the sample photo -> view folder (detected keypoints, fitted body, 4 views)" \
  "$DLA" dream "$PHOTO" -o "$OUT/views"
step "2/3 lift: views -> avatar.npz (+ contact sheet)" \
  "$DLA" lift "$OUT/views" -o "$OUT/avatar.npz"
step "3/3 animate: avatar + built-in walk -> USD + preview video" \
  "$DLA" animate "$OUT/avatar.npz" walk -o "$OUT/walk.usdc" --preview "$OUT/walk.mp4"
"$DLA" export "$OUT/avatar.npz" -o "$OUT/avatar.ply" >/dev/null
"$DLA" info "$OUT/walk.usdc"
cat >&2 <<MSG
done. Look at:
  $OUT/views/fit_overlay.png      the fitted body over the photo
  $OUT/avatar_contact.png         input views (top) vs the avatar re-rendered (bottom)
  $OUT/walk.mp4                   the avatar walking
  $OUT/walk.usdc                  the animation for USD tools (coloured points; Blender: docs/animate.md)
  $OUT/avatar.ply                 the avatar's Gaussians for splat viewers (upright in SuperSplat)
More: dla view $OUT/avatar.npz --motion walk -o walk.html   (plays in a browser)
      dla export $OUT/avatar.npz --rig --motion walk -o rig.usdc   (an armature for Blender)
MSG
