"""Synthetic subjects and datasets with ground truth (docs/synth.md, formats/dataset.md).

The anny body dressed in MakeHuman garments, textured, lit and rendered; every random choice comes
from `numpy.random.default_rng` generators seeded by the subject's seed, so a seed gives the same
bytes on every run. One concept per module, imported in this order:

- `subject`: the seeded subject (`SubjectSpec`: phenotype, relaxed pose, outfit, palette);
- `garments`: the subject's body and garments as one posable mesh (`DressedBody`);
- `poses`: the target poses (seeded pose kinds, frames of motion clips);
- `appearance`: procedural albedo, the "lit" lights and the ambient occlusion;
- `images`: the supersampled rasterisation into RGBA images (`render`);
- `cameras`: the synth rig (input, novel-view and novel-pose cameras);
- `synth`: one subject as a view folder (`dla synth`);
- `dataset`: many subjects in a dataset folder with a manifest (`dla synth --seeds`).

Layer (docs/architecture.md, "The layers"): beside `dlacli.stages`; `poses` reads motion clips through the stage
`dlacli.stages.motion.source` (the one edge between the two, listed in tests/test_layers.py).
"""
