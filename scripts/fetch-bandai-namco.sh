#!/usr/bin/env bash
# Fetches the twelve clips of the Bandai Namco Research Motion dataset that `dla`'s video-fit
# evaluation renders as synthetic videos (docs/motion.md, "Bandai Namco clips"), with the
# dataset's licence, into DEST.
#
#   bash scripts/fetch-bandai-namco.sh DEST
#
# The dataset is CC BY-NC 4.0 (non-commercial): it may evaluate dla, never train the weights dla
# ships, and it is never copied into this repository; the tests do not need it. The files come
# from one pinned commit of github.com/BandaiNamcoResearchInc/Bandai-Namco-Research-Motiondataset
# (a shallow, sparse clone: only the twelve files are downloaded) and each is checked against its
# SHA-256. BANDAI_NAMCO_REPO overrides the clone URL (a local mirror). Running it again when
# the files are in place does nothing.
set -euo pipefail
DEST="${1:?usage: fetch-bandai-namco.sh DEST}"
REPO="${BANDAI_NAMCO_REPO:-https://github.com/BandaiNamcoResearchInc/Bandai-Namco-Research-Motiondataset.git}"
COMMIT=74ead3ba1ae4696404e6086233779f60de8bf9ef
DIR=dataset/Bandai-Namco-Research-Motiondataset-1
declare -A SHA256=(
  [dataset-1_walk_normal_001.bvh]=5764cebc2fedabf287880a7f25cb06753e1679675a02a6f033998de041ba8032
  [dataset-1_walk-back_normal_001.bvh]=4c182559dbd28e4ba485f664dea49817a30fc0acde29b482f1baaeff4fa80397
  [dataset-1_bow_normal_001.bvh]=4e390b9c92caf7bb92b49bb0b5df72cf6e9f48900656b55a100a77b6bab0946b
  [dataset-1_byebye_normal_001.bvh]=f07fb9889b823a6efbbc7d5439c674cfd0540081c484ed4c6ec137f2b55f666c
  [dataset-1_guide_normal_001.bvh]=30069344e592775775a5868cf625b06d902bea61ca6b68ffae3b6d0560306ad9
  [dataset-1_respond_normal_001.bvh]=18b718f955b0abee378ce0f7229f4dbf5ad144d9fce541c4a9e4de13b0c21221
  [dataset-1_kick_normal_001.bvh]=1194a1dae534ee065d4e6eed68c21d7437b1bb81d15754bcabef32185b200911
  [dataset-1_punch_normal_001.bvh]=000e0093365b7e2a4e6dc7e0fbde15a70d2959630b7bd12750762d1c14e7c652
  [dataset-1_bye_normal_001.bvh]=cf821ed70f42832e9b519103ffb5e0a0f458ab46582340071b8867a633e8ee4d
  [dataset-1_call_normal_001.bvh]=7f12a26a95051efe5ec04f277bdd4ed6a9a9f6141faeefe3511efcb729e79765
  [dataset-1_slash_normal_001.bvh]=b2fea21820d898cee5229829268b861d783041317bc560ea977d5789fd630d6d
  [dataset-1_dance-short_normal_001.bvh]=a9bef1cd697e4274bc1e773c2eb30f9b2c525f1fd57deaf788a6f63ce87fa63f
)

have() {
  for f in "${!SHA256[@]}"; do
    [ -f "$DEST/$f" ] && echo "${SHA256[$f]}  $DEST/$f" | sha256sum --quiet -c - >/dev/null 2>&1 || return 1
  done
}
if have; then
  echo "fetch-bandai-namco: the ${#SHA256[@]} clips are in $DEST"
  exit 0
fi

tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
git -C "$tmp" init -q
git -C "$tmp" remote add origin "$REPO"
git -C "$tmp" sparse-checkout set --no-cone "/$DIR/LICENSE" $(printf "/$DIR/data/%s " "${!SHA256[@]}")
git -C "$tmp" -c protocol.file.allow=always fetch -q --depth 1 --filter=blob:none origin "$COMMIT"
git -C "$tmp" checkout -q FETCH_HEAD
for f in "${!SHA256[@]}"; do
  if ! echo "${SHA256[$f]}  $tmp/$DIR/data/$f" | sha256sum --quiet -c - >/dev/null 2>&1; then
    echo "fetch-bandai-namco: $f does not have the expected SHA-256; nothing installed" >&2
    exit 1
  fi
done
mkdir -p "$DEST"
for f in "${!SHA256[@]}"; do cp "$tmp/$DIR/data/$f" "$DEST/$f"; done
cp "$tmp/$DIR/LICENSE" "$DEST/LICENSE"
echo "fetch-bandai-namco: ${#SHA256[@]} clips (CC BY-NC 4.0, evaluation only) in $DEST"
