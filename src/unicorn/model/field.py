"""Shape branch: a code regressor and a deformation field over template vertices."""

from __future__ import annotations

import torch
from torch import nn

from unicorn.checks import check_shape
from unicorn.geometry.mesh import mirror_points
from unicorn.model.mlp import MLP
from unicorn.model.progressive import ProgressiveMask

__all__ = ["DeformationField", "ShapeHead"]


class DeformationField(nn.Module):
    """MLP of (template vertex, shape code) -> displacement.

    ``h = ReLU(linear_x(x) + linear_z(z))`` then ``Linear-ReLU-Linear-ReLU-Linear`` to 3 values; the last
    layer is zeroed so that the displacement is exactly 0 at init. No output activation.

    Args:
        code_dim: shape code size.
        n_units: hidden width (128 for real images, 512 for ShapeNet).
        n_layers: hidden layers after the input layer (2 in UNICORN).
    """

    def __init__(self, code_dim: int, n_units: int = 128, n_layers: int = 2) -> None:
        super().__init__()
        self.code_dim = code_dim
        self.linear_x = nn.Linear(3, n_units)
        self.linear_z = nn.Linear(max(code_dim, 1), n_units)
        for layer in (self.linear_x, self.linear_z):
            nn.init.kaiming_normal_(layer.weight, nonlinearity="relu")
            nn.init.zeros_(layer.bias)
        self.mlp = MLP(n_units, 3, n_units=n_units, n_layers=n_layers, zero_last=True)

    def forward(self, points: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        """Displacements of ``points``.

        Args:
            points: (B, V, 3) or (V, 3) template vertices (shared by the batch when 2-D).
            code: (B, code_dim) shape codes.

        Returns:
            (B, V, 3) displacements.
        """
        dims = check_shape(code, "B, C", "code", {"C": self.code_dim})
        if points.dim() == 2:
            points = points.unsqueeze(0).expand(code.shape[0], -1, -1)
        check_shape(points, "B, V, 3", "points", dims)
        z = code if self.code_dim > 0 else code.new_zeros(code.shape[0], 1)
        h = torch.relu(self.linear_x(points) + self.linear_z(z).unsqueeze(1))
        return self.mlp(h)


class ShapeHead(nn.Module):
    """Image features -> masked shape code -> per-vertex displacement of the template.

    ``use_deformation`` (a buffer) holds the displacement at 0 during the first stage.

    Names follow the reference (``regressor``, ``field.linear_x``, ``field.linear_z``, ``field.mlp``).

    Args:
        in_features: encoder feature size (512).
        code_dim: full shape code size (32 small / 64 big).
        n_field_units, n_field_layers: deformation field width and depth.
        n_reg_units, n_reg_layers: code regressor width and depth (zero-initialised last layer).
        symmetric: mirror-symmetric displacements through the plane z = 0 (the mean of the field at a point and
            the mirror of the field at the point's mirror image), so a template symmetric in z stays so; the
            paper uses no symmetry prior (False).
    """

    use_deformation: torch.Tensor

    def __init__(
        self,
        in_features: int = 512,
        code_dim: int = 32,
        n_field_units: int = 128,
        n_field_layers: int = 2,
        n_reg_units: int = 128,
        n_reg_layers: int = 3,
        symmetric: bool = False,
    ) -> None:
        super().__init__()
        self.symmetric = symmetric
        self.regressor = MLP(in_features, code_dim, n_reg_units, n_reg_layers, zero_last=True)
        self.mask = ProgressiveMask(code_dim, active_dims=0)
        self.field = DeformationField(code_dim, n_field_units, n_field_layers)
        # stage-1 switch: while False the mesh is the plain template
        self.register_buffer("use_deformation", torch.tensor(True))

    @property
    def code_dim(self) -> int:
        return self.mask.code_dim

    def code(self, features: torch.Tensor) -> torch.Tensor:
        """(B, in_features) -> masked shape code (B, code_dim)."""
        return self.mask(self.regressor(features))

    def forward(self, template: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        """Displacements (B, V, 3) of ``template`` (V, 3) for masked codes (B, code_dim)."""
        if self.symmetric:
            # one field call on the points and their mirror images, split after
            both = self.field(torch.cat([template, mirror_points(template)], dim=-2), code)
            delta, delta_of_mirror = both.split(template.shape[-2], dim=-2)
            delta = (delta + mirror_points(delta_of_mirror)) / 2
        else:
            delta = self.field(template, code)
        return delta * self.use_deformation.to(delta.dtype)
