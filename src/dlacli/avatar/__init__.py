"""The avatar representation (docs/architecture.md, "The layers": avatar/): the UV Gaussian map F's channel
layout and surface samples (gaussian_map), the codec that maps an avatar's encoder, decoder and
checkpoint to code (codec), and the one path from an avatar, posed bodies and cameras to Gaussians
with the sample-count/seed policy (posed). Below nn/: the networks register their decoders here,
never the other way round."""
