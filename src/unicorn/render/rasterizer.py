"""The rasterizer module: camera projection plus :func:`rasterize_meshes`, with its settings.

Soft top-K rasterization (``faces_per_pixel`` faces within ``blur_radius`` of each pixel) and hard
rasterization (one face, no blur, optionally supersampled) are the same module with different settings.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import nn

from ..geometry.cameras import PerspectiveCamera, image_hw, world_to_view
from ..hostsync import is_sync_free
from .fragments import Fragments
from .precision import float32_boundary
from .raster import check_blur_radius, check_mesh_inputs, check_pose_inputs, rasterize_meshes
from .settings import DEFAULT_SETTINGS, check_render_option

__all__ = ["MeshRasterizer"]


class MeshRasterizer(nn.Module):
    """Meshes seen from a camera to packed :class:`Fragments`.

    The options' ranges are those of :class:`~unicorn.render.settings.RenderSettings`.

    Args:
        image_size: H or (H, W), the size of the images rendered from the fragments.
        faces_per_pixel: K, the most faces kept per pixel.
        blur_radius: squared NDC radius within which a face outside the pixel still counts.
        camera: projection; a 30-degree field of view by default (the reference's).
        truncate_opaque: drop the faces behind the first one containing the pixel (for aggregators in which
            that face hides them exactly), and keep that face in the last slot when more near misses lie in front.
        supersample: integer factor s: fragments are computed at (s * H, s * W) (1 = none).
        max_candidates: rasterizer work budget per chunk of images (bounds memory).
        max_bytes: refuse renders whose fragments could exceed this many bytes, ``B x H x W x K x 64`` at the
            raster size (:func:`~unicorn.render.raster.check_render_size`); None: ``$UNICORN_MAX_RENDER_BYTES``
            or 16 GiB; 0: no limit.
        perspective_correct: perspective-correct barycentrics (the 3D point seen at the pixel, PyTorch3D's
            option of that name) instead of screen-space ones; see :func:`~unicorn.render.raster.rasterize_meshes`.
    """

    def __init__(
        self,
        image_size: int | Sequence[int] = 64,
        faces_per_pixel: int = 1,
        blur_radius: float = 0.0,
        camera: PerspectiveCamera | None = None,
        truncate_opaque: bool = False,
        supersample: int = 1,
        max_candidates: int = DEFAULT_SETTINGS.max_candidates,
        max_bytes: int | None = None,
        perspective_correct: bool = False,
    ) -> None:
        super().__init__()
        self.image_size = image_hw(image_size)
        settings = {"faces_per_pixel": faces_per_pixel, "supersample": supersample, "max_candidates": max_candidates}
        settings.update(max_bytes=max_bytes, perspective_correct=perspective_correct)
        for name, value in settings.items():
            check_render_option(name, value)
        self.faces_per_pixel = int(faces_per_pixel)
        check_blur_radius(blur_radius)
        self.blur_radius = float(blur_radius)
        if camera is not None and not isinstance(camera, PerspectiveCamera):
            raise TypeError(f"camera must be a PerspectiveCamera or None, got {type(camera).__name__}")
        self.camera = camera if camera is not None else PerspectiveCamera(fov=30.0)
        self.truncate_opaque = bool(truncate_opaque)
        self.supersample = int(supersample)
        self.max_candidates = int(max_candidates)
        self.max_bytes = None if max_bytes is None else int(max_bytes)
        self.perspective_correct = perspective_correct
        #: (B, H, W) -> the fixed buffers (candidates, pairs) of renders inside unicorn.hostsync.sync_free, sized
        #: from the renders outside it (and grown by :meth:`grow_buffers`); a size not seen yet renders as usual
        self.buffers: dict[tuple[int, int, int], tuple[int, int]] = {}
        self._needed: dict[tuple[int, int, int], torch.Tensor] = {}  # what the fixed renders needed, on the device

    def extra_repr(self) -> str:
        return (
            f"image_size={self.image_size}, faces_per_pixel={self.faces_per_pixel}, "
            f"blur_radius={self.blur_radius:.3g}, truncate_opaque={self.truncate_opaque}, "
            f"supersample={self.supersample}, perspective_correct={self.perspective_correct}"
        )

    @property
    def raster_size(self) -> tuple[int, int]:
        """(s * H, s * W), the size of the fragments."""
        H, W = self.image_size
        return H * self.supersample, W * self.supersample

    def project(self, verts: torch.Tensor, R: torch.Tensor | None, T: torch.Tensor | None) -> torch.Tensor:
        """World vertices (B, V, 3) to ``(x_ndc, y_ndc, z_view)`` (B, V, 3); with R, T None verts are in view space."""
        if (R is None) != (T is None):
            raise ValueError("give both R and T, or neither (verts already in view coordinates)")
        view = verts if R is None else world_to_view(verts, R, T)
        return self.camera.project(view)

    @float32_boundary
    def forward(
        self,
        verts: torch.Tensor,
        faces: torch.Tensor,
        R: torch.Tensor | None = None,
        T: torch.Tensor | None = None,
        image_size: int | tuple[int, int] | None = None,
        check_inputs: bool = True,
    ) -> Fragments:
        """Fragments of the meshes seen with pose (R, T).

        Args:
            verts: (B, V, 3) world vertices (view vertices if R and T are None).
            faces: (F, 3) integer, shared by the batch.
            R: (B, 3, 3) world-to-view rotation, ``x_view = x @ R + T``, applied in the vertices' dtype.
            T: (B, 3) world-to-view translation, likewise.
            image_size: H or (H, W) of the fragments; :attr:`raster_size` when None.
            check_inputs: validate the meshes and the pose (False when the caller did: each check is a host
                sync on CUDA).

        Under ``torch.autocast`` float16 and bfloat16 vertices and poses are cast to float32 and the projection and
        depth tests run with autocast off (:func:`unicorn.render.precision.float32_boundary`).
        """
        if check_inputs:
            check_mesh_inputs(verts, faces)
            check_pose_inputs(R, T, verts.shape[0])
        size = self.raster_size if image_size is None else image_hw(image_size)
        key = (verts.shape[0], *size)
        capacity = self.buffers.get(key) if is_sync_free() else None
        fragments = rasterize_meshes(
            self.project(verts, R, T), faces, size, self.blur_radius,
            self.faces_per_pixel, self.truncate_opaque, self.max_candidates, check_inputs=False,
            max_bytes=self.max_bytes, perspective_correct=self.perspective_correct, capacity=capacity,
        )  # fmt: skip
        # the default path (a fixed render with nothing to draw takes it too) reads its sizes to the host: they size
        # the fixed buffers
        if fragments.sizes is not None and fragments.valid is None:
            self._fit(key, fragments.sizes.tolist())
            # an entry from the start, kept from then on: a compiled step's graph guards on the keys present
            # on the meshes' device (these sizes are on the host): the fixed renders fold theirs in there
            if key not in self._needed:
                # a normal tensor even when first made under inference_mode (validation): updated in place outside
                with torch.inference_mode(False):
                    self._needed[key] = torch.zeros(2, dtype=torch.long, device=verts.device)
        elif fragments.sizes is not None:
            before = self._needed.get(key)
            if before is None:
                self._needed[key] = fragments.sizes
            else:  # in place: a compiled step's CUDA graphs replay on the same tensors
                before.copy_(torch.maximum(before, fragments.sizes))
        return fragments

    def _fit(self, key: tuple[int, int, int], needed: list[int]) -> bool:
        """Grow the buffers of ``key`` to hold ``needed`` (candidates, pairs) with a margin; whether they grew."""
        have = self.buffers.get(key, (0, 0))
        if all(n <= h for n, h in zip(needed, have)):
            return False
        # a quarter more, in steps of 1024: a few sizes for the whole run
        self.buffers[key] = tuple(max(h, -(-int(n * 1.25) // 1024) * 1024) for n, h in zip(needed, have))
        return True

    def _apply(self, fn: Callable[[torch.Tensor], torch.Tensor], recurse: bool = True) -> MeshRasterizer:
        super()._apply(fn, recurse)
        # the fixed renders' needed sizes are no buffers (not in the state dict) but follow the module's device
        self._needed = {key: fn(sizes) for key, sizes in self._needed.items()}
        return self

    def grow_buffers(self) -> list[str]:
        """Read what the fixed-buffer renders since the previous call needed (one host read) and grow the buffers
        that were too small (those renders dropped candidates or pairs); a line for each of them."""
        needed = self._needed
        if not needed:
            return []
        keys = list(needed)
        read = torch.stack([needed[k] for k in keys]).tolist()
        for sizes in needed.values():  # from zero again, in the same tensors (see forward)
            sizes.zero_()
        lines = []
        for key, sizes in zip(keys, read):
            have = self.buffers.get(key, (0, 0))
            if self._fit(key, sizes) and any(n > h for n, h in zip(sizes, have)):
                lines.append(
                    f"renders of {key[0]} x {key[1]}x{key[2]} needed {sizes[0]} candidates and {sizes[1]} pairs, over "
                    f"the buffers of {have[0]} and {have[1]}, and lost some; grown to {self.buffers[key]}"
                )
        return lines
