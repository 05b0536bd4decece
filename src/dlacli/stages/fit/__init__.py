"""The body fit to a photo, shared by dream (one photo) and motion from a video (per frame; docs/fit.md).

photo.py       fit anny's body to one photo: keypoints + person mask -> body parameters and camera
silhouette.py  the fit's silhouette terms
report.py      what a fit says about itself: the overlay, the recorded info, the warning
"""
