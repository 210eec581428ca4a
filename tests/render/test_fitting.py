"""Optimising through the renderer: shapes deform to match images, and the paper's SoftRas argument."""

import torch

from unicorn.geometry.mesh import icosphere
from unicorn.geometry.rotations import look_at_view_transform
from unicorn.render import LayeredRasterizer, SoftRasRenderer, TexturesVertex


def test_sphere_deforms_to_match_target_silhouette_and_image():
    torch.manual_seed(0)
    v, f = icosphere(2)
    views = 4
    R, T = look_at_view_transform(2.732, 20.0, torch.arange(views) * 90.0 + 30.0)
    renderer = LayeredRasterizer(image_size=32, sigma=1e-4, faces_per_pixel=25, background_color=(0.0, 0.0, 0.0))
    # target: an ellipsoid coloured by height, rendered from the same views
    target_verts = v * torch.tensor([0.75, 0.4, 0.55])
    color = lambda x: torch.stack([0.5 + x[..., 1], 0.3 + 0.0 * x[..., 1], 0.8 - x[..., 1]], -1).clamp(0, 1)  # noqa: E731
    target = renderer(
        target_verts[None].expand(views, -1, -1),
        f,
        TexturesVertex(color(target_verts)[None].expand(views, -1, -1)),
        R=R,
        T=T,
    )

    offsets = torch.zeros_like(v, requires_grad=True)
    colors = torch.full((1, v.shape[0], 3), 0.5, requires_grad=True)
    opt = torch.optim.Adam([offsets, colors], lr=0.01)
    base = v * 0.5

    def loss_fn():
        verts = (base + offsets)[None].expand(views, -1, -1)
        images = renderer(verts, f, TexturesVertex(colors.expand(views, -1, -1)), R=R, T=T)
        return ((images - target) ** 2).mean()

    initial = loss_fn().item()
    for _ in range(100):
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        opt.step()
    final = loss_fn().item()
    # stated reduction: the loss falls below 10 % of its initial value
    assert final < 0.1 * initial, (initial, final)
    # and the silhouette really moved: the fitted extent along X approaches the target's 0.75
    extent = (base + offsets).detach()[:, 0].abs().max().item()
    assert 0.65 < extent < 0.85


def test_softras_gradient_through_occupancy_is_orders_of_magnitude_weaker():
    # one white face over a black background, target = the same face shifted: only occupancy carries the signal
    verts = torch.tensor([[[0.2, -0.3, 2.5], [-0.3, -0.2, 2.5], [0.0, 0.35, 2.5]]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2]])
    white = TexturesVertex(torch.ones(1, 3, 3, dtype=torch.float64))
    shift = torch.tensor([0.04, 0.02, 0.0], dtype=torch.float64)
    eye, zero = torch.eye(3, dtype=torch.float64)[None], torch.zeros(1, 3, dtype=torch.float64)
    grads = {}
    for name, renderer in {
        "layered": LayeredRasterizer(image_size=64, background_color=(0.0, 0.0, 0.0)),
        "softras": SoftRasRenderer(image_size=64, background_color=(0.0, 0.0, 0.0)),  # paper defaults
    }.items():
        target = renderer(verts + shift, faces, white, R=eye, T=zero)[:, :3].detach()
        v = verts.clone().requires_grad_()
        loss = ((renderer(v, faces, white, R=eye, T=zero)[:, :3] - target) ** 2).sum()
        loss.backward()
        grads[name] = v.grad.norm().item()
    assert grads["layered"] > 1.0
    assert grads["softras"] < 1e-3 * grads["layered"], grads
