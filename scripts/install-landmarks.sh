#!/usr/bin/env bash
# Installs MediaPipe Pose's "lite" and "heavy" landmark models next to the "full" one that the
# mediapipe wheel ships, so that `dla dream` and `dla motion from-video` can take
# `--landmarks lite|heavy` (docs/motion.md, "Landmark models"). dla itself never downloads them.
#
#   bash scripts/install-landmarks.sh [PYTHON]      (default: .venv/bin/python)
#
# The models come from the npm package @mediapipe/pose 0.5.1675469404 (Apache-2.0), fetched from
# the npm registry as a package install is; the tarball is checked against the registry's SHA-512
# and each model against its SHA-256 (the values io/detect.py checks again before using one), then
# copied into mediapipe's modules/pose_landmark/ folder of that Python's environment. Running it
# again when both models are in place does nothing.
set -euo pipefail
PY="${1:-.venv/bin/python}"
VERSION="0.5.1675469404"
URL="https://registry.npmjs.org/@mediapipe/pose/-/pose-${VERSION}.tgz"
TARBALL_SHA512="DFZsNWTsSphRIZppnUCuunzBiHP2FdJXR9ehc7mMi4KG+oPaOH0Em3d6kr7Py+TSyTXC1doH88KcF28k2sBxsQ=="
declare -A SHA256=(
  [lite]=f17bfbecadb61c3be1baa8b8d851cc6619c870a87167b32848ad20db306b9d61
  [heavy]=59e42d71bcd44cbdbabc419f0ff76686595fd265419566bd4009ef703ea8e1fe
)

dest="$("$PY" - <<'EOF'
import importlib.util, pathlib, sys
spec = importlib.util.find_spec("mediapipe")
if spec is None or not spec.submodule_search_locations:
    sys.exit("install-landmarks: mediapipe is not installed in this environment")
print(pathlib.Path(list(spec.submodule_search_locations)[0]) / "modules" / "pose_landmark")
EOF
)"

sha256_of() { "$PY" -c 'import hashlib, sys; print(hashlib.sha256(open(sys.argv[1], "rb").read()).hexdigest())' "$1"; }

missing=()
for name in lite heavy; do
  file="$dest/pose_landmark_${name}.tflite"
  if [ ! -f "$file" ] || [ "$(sha256_of "$file")" != "${SHA256[$name]}" ]; then
    missing+=("$name")
  fi
done
if [ "${#missing[@]}" -eq 0 ]; then
  echo "install-landmarks: lite and heavy are in place in $dest"
  exit 0
fi

tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
"$PY" - "$URL" "$tmp/pose.tgz" "$TARBALL_SHA512" <<'EOF'
import base64, hashlib, sys, urllib.request
url, out, want = sys.argv[1:4]
with urllib.request.urlopen(url, timeout=120) as response, open(out, "wb") as f:
    f.write(response.read(64 << 20))
got = base64.b64encode(hashlib.sha512(open(out, "rb").read()).digest()).decode()
if got != want:
    sys.exit(f"install-landmarks: {url}: SHA-512 {got} is not the registry's {want}")
EOF
for name in "${missing[@]}"; do
  tar -xzf "$tmp/pose.tgz" -C "$tmp" "package/pose_landmark_${name}.tflite"
  got="$(sha256_of "$tmp/package/pose_landmark_${name}.tflite")"
  if [ "$got" != "${SHA256[$name]}" ]; then
    echo "install-landmarks: pose_landmark_${name}.tflite: SHA-256 $got, expected ${SHA256[$name]}" >&2
    exit 1
  fi
  cp "$tmp/package/pose_landmark_${name}.tflite" "$dest/.pose_landmark_${name}.tflite.part"
  chmod 644 "$dest/.pose_landmark_${name}.tflite.part"
  mv "$dest/.pose_landmark_${name}.tflite.part" "$dest/pose_landmark_${name}.tflite"
  echo "install-landmarks: $name -> $dest/pose_landmark_${name}.tflite"
done
