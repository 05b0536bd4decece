"""`dla lift`: a view folder -> an avatar. The registry of lift methods (`methods`), mesh
unprojection and what every lift shares (`unproject`: unstructured Gaussians, the bake, the
refinement, the driver and its result), the learned and the residual lifts (`learned`,
`residual`), and their pieces: the visual hull (`hull`), the texel bake (`bake`), the residual
network's observation features (`observations`), the shared Adam loop and crops (`refine`) and
the contact sheet (`sheet`)."""
