"""Motion: where `dla animate` and `dla motion` get their poses (docs/motion.md).

source.py   `load_motion`: any motion the toolkit accepts, as a native motion on anny's rig
video.py    `dla motion from-video`: a video of a person -> motion.npz
fit.py      one temporal fit of anny's pose to the clip's per-frame detections
preview.py  a quick look at a motion: the default body doing it (for checking retargets)
"""
