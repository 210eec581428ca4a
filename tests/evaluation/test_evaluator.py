"""Evaluation loops of every protocol, on the synthetic set and the CUB / Pascal3D+ fixture layouts."""

from __future__ import annotations

import copy
import dataclasses
import math

import pytest
import torch
from torch.utils.data import Dataset

from unicorn.evaluation import (
    EvalOptions,
    build_eval_dataset,
    candidate_shares,
    evaluate,
    hard_render,
    protocol_for,
    vertex_visibility,
)
from unicorn.evaluation.baselines import FixedShapeModel
from unicorn.evaluation.evaluator import collate
from unicorn.evaluation.interface import spread_indices
from unicorn.geometry.cameras import PerspectiveCamera
from unicorn.metrics import (
    align_canonical_frame,
    evaluate_meshes,
    geodesic_error,
    keypoint_transfer_pck,
    mask_iou,
    sample_points_from_meshes,
    shape_retrieval,
)
from unicorn.model import Prediction, Unicorn

FAST = dict(batch_size=3, num_points=400, icp_iterations=2, num_pairs=50, progress=False)


def test_shapenet_protocol(shapenet_model, synth_root) -> None:
    data = build_eval_dataset("synthetic", str(synth_root), "train", img_size=32)
    result = evaluate(shapenet_model, data, EvalOptions("shapenet", report_samples=2, **FAST), "synthetic")
    assert [row["group"] for row in result.table] == ["chair", "mug", "mean"]
    assert result.columns[:7] == [
        "chamfer-L1", "chamfer-L1-ICP", "normal-cos", "normal-cos-ICP", "iou-3d", "iou-3d-ICP", "mask-iou",
    ]  # fmt: skip
    assert {"rot-err-median", "rot-acc-30", "rec-mse"} <= set(result.columns)
    assert len(result.per_image) == len(data) == 4 and result.mean["n-images"] == 4
    for key in result.columns:
        groups = [row[key] for row in result.table[:-1]]
        assert result.mean[key] == pytest.approx(sum(groups) / len(groups))  # categories, then their mean
        assert all(math.isfinite(v) for v in groups)
    assert 0 <= result.mean["mask-iou"] <= 1 and len(result.samples) == 2
    # the report's samples carry their image's whole row, the scores computed over the group included
    for row, sample in zip(result.per_image, result.samples):
        assert sample.scores == {k: v for k, v in row.items() if k not in ("index", "group")}
        assert {"rot-err", "color-err", "color-err-mean-overlap"} <= set(sample.scores)
    # each image's rotation error (after its group's alignment) is in its row, and the set metrics summarise it
    for row in result.table[:-1]:
        errors = torch.tensor([r["rot-err"] for r in result.per_image if r["group"] == row["group"]])
        assert row["rot-err-mean"] == pytest.approx(float(errors.mean()), abs=1e-4)
        assert row["rot-acc-30"] == pytest.approx(float((errors < 30).double().mean()))
    assert "rot-err" not in result.columns
    # ... and that error is the one after the group's alignment, recomputed here from the predictions
    items = collate([data[i] for i in range(len(data))])
    with torch.no_grad():
        R_pred = shapenet_model.predict(items["image"]).R
    for g in ("chair", "mug"):
        idx = [i for i, r in enumerate(result.per_image) if r["group"] == g]
        Q = align_canonical_frame(R_pred[idx], items["R"][idx])
        want = geodesic_error(Q @ R_pred[idx], items["R"][idx])
        assert [result.per_image[i]["rot-err"] for i in idx] == pytest.approx(want.tolist(), abs=1e-3)

    # the loop's numbers are the metric functions' on the same prediction (GT-pose alignment wired right)
    batch = collate([data[i] for i in range(3)])  # the loop's first batch (the point sampling is per batch)
    with torch.no_grad():
        pred = shapenet_model.predict(batch["image"])
    direct = evaluate_meshes(
        pred.verts, shapenet_model.template.faces, batch["points"], batch["normals"],
        R_pred=pred.R, T_pred=pred.T, R_gt=batch["R"], T_gt=batch["T"], num_points=400, icp_iterations=2,
    )  # fmt: skip
    for i in range(3):
        assert result.per_image[i]["chamfer-L1"] == pytest.approx(float(direct["chamfer-L1"][i]), rel=1e-5)
        assert result.per_image[i]["iou-3d"] == pytest.approx(float(direct["iou-3d"][i]), abs=1e-12)
        assert 0 <= result.per_image[i]["iou-3d-ICP"] <= 1
    sample = result.samples[0]
    iou = mask_iou(sample.alpha[None], sample.mask[None])
    assert result.per_image[0]["mask-iou"] == pytest.approx(float(iou), abs=1e-6)


def _rotation(axis: list[float], degrees: float) -> torch.Tensor:
    """(3, 3) rotation by ``degrees`` about ``axis`` (Rodrigues' formula)."""
    k = torch.tensor(axis, dtype=torch.float64)
    k = k / k.norm()
    K = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]], dtype=torch.float64)
    a = math.radians(degrees)
    return (torch.eye(3, dtype=torch.float64) + math.sin(a) * K + (1 - math.cos(a)) * K @ K).float()


class _TurnedFrame(FixedShapeModel):
    """A model whose every pose candidate is the ground truth seen in a frame turned by ``Q0``: ``Q0^T R_gt``.

    Each image it is given is matched to the nearest of ``images`` (the evaluated items), whose ``R_gt`` it takes.
    """

    def __init__(self, model: Unicorn, images: torch.Tensor, R_gt: torch.Tensor, Q0: torch.Tensor) -> None:
        super().__init__(model, model.template.verts, pose="predicted")
        self.images, self.R_gt, self.Q0 = images, R_gt, Q0

    def predict(self, images: torch.Tensor, average_texture: bool = False) -> Prediction:
        pred = super().predict(images, average_texture=average_texture)
        nearest = torch.cdist(images.flatten(1), self.images.flatten(1)).argmin(1)
        R = (self.Q0.T @ self.R_gt[nearest]).to(pred.R)
        K = pred.poses.R.shape[0]
        poses = dataclasses.replace(pred.poses, R=R.expand(K, -1, -1, -1).clone())
        return dataclasses.replace(pred, poses=poses, R=R)


def test_pose_errors_after_a_known_turn_of_the_frame(shapenet_model, synth_root) -> None:
    """Predictions right up to one global rotation Q0: ~0 error once aligned, Q0's angle for every image without."""
    data = build_eval_dataset("synthetic", str(synth_root), "train", img_size=32)
    items = collate([data[i] for i in range(len(data))])
    Q0 = _rotation([1.0, 2.0, -0.5], 100.0)
    assert float(geodesic_error(Q0, torch.eye(3))) == pytest.approx(100.0, abs=1e-3)
    turned = _TurnedFrame(shapenet_model, items["image"], items["R"], Q0)
    options = dict(FAST, icp_iterations=0)
    aligned = evaluate(turned, data, EvalOptions("shapenet", **options), "synthetic")
    raw = evaluate(turned, data, EvalOptions("shapenet", align_pose=False, **options), "synthetic")
    assert len(aligned.per_image) == len(raw.per_image) == len(data) == 4
    for a, r in zip(aligned.per_image, raw.per_image, strict=True):
        assert a["rot-err"] == pytest.approx(0.0, abs=0.05)
        assert r["rot-err"] == pytest.approx(100.0, abs=0.05)
    for a, r in zip(aligned.table, raw.table, strict=True):
        assert a["rot-err-median"] == pytest.approx(0.0, abs=0.05) and a["rot-acc-30"] == 1.0
        assert r["rot-err-median"] == pytest.approx(100.0, abs=0.05) and r["rot-acc-30"] == 0.0


def test_a_group_of_one_image_has_no_aligned_pose_error(shapenet_model, synth_root) -> None:
    """One rotation fitted to one image aligns it exactly: its aligned error would be 0 for any prediction."""
    data = build_eval_dataset("synthetic", str(synth_root), "test", img_size=32)  # one image per category
    items = collate([data[i] for i in range(len(data))])
    turned = _TurnedFrame(shapenet_model, items["image"], items["R"], _rotation([1.0, 2.0, -0.5], 100.0))
    options = dict(FAST, icp_iterations=0)
    aligned = evaluate(turned, data, EvalOptions("shapenet", **options), "synthetic")
    raw = evaluate(turned, data, EvalOptions("shapenet", align_pose=False, **options), "synthetic")
    pose_columns = ["rot-err-mean", "rot-err-median", "rot-acc-30", "rot-flip-150", "rot-acc-30-any"]
    pose_columns += ["azim-err-mean", "azim-err-median"]
    assert [row["n-images"] for row in aligned.table] == [1, 1, 2]
    assert set(pose_columns) <= set(aligned.columns)  # shown, as undefined ("-")
    for row in aligned.table:
        assert all(math.isnan(row[c]) for c in pose_columns)
    assert all("rot-err" not in r for r in aligned.per_image)
    # without the alignment, the error is the frame's turn
    assert [r["rot-err"] for r in raw.per_image] == pytest.approx([100.0, 100.0], abs=0.05)
    assert all(row["rot-acc-30"] == 0.0 for row in raw.table)


def _interior(fg: torch.Tensor, r: int) -> list[tuple[int, int]]:
    """Pixels of a (H, W) bool mask whose (2r+1)^2 neighbourhood (clipped to the frame) is all foreground."""
    H, W = fg.shape
    inside = [
        (y, x)
        for y in range(H)
        for x in range(W)
        if bool(fg[max(y - r, 0) : y + r + 1, max(x - r, 0) : x + r + 1].all())
    ]
    return inside or [(y, x) for y in range(H) for x in range(W) if bool(fg[y, x])]


def test_instance_metrics_against_a_direct_computation(shapenet_model, synth_root) -> None:
    data = build_eval_dataset("synthetic", str(synth_root), "train", img_size=32)
    template = shapenet_model.template.verts.clone()
    result = evaluate(shapenet_model, data, EvalOptions("shapenet", **FAST), "synthetic", shape_baseline=template * 0.9)
    for key in ("color-err", "color-err-mean", "color-ratio", "chamfer-L1-ICP-mean-shape", "shape-win", "rot-flip-150"):
        assert key in result.columns

    # colours, with pixel loops over the same hard renders and the input masks
    batches = [collate([data[i] for i in range(0, 3)]), collate([data[i] for i in range(3, len(data))])]
    pred_colors, gt_colors, groups = [], [], []
    pred_both, gt_both = [], []  # the same over the pixels both silhouettes cover
    for batch in batches:
        with torch.no_grad():
            pred = shapenet_model.predict(batch["image"])
            hard = hard_render(shapenet_model, pred.verts, pred.texture, pred.R, pred.T, batch["mask"].shape[-1], 3)
        for i in range(len(batch["index"])):
            rgb, alpha, mask = hard.images[i, :3], hard.images[i, 3], batch["mask"][i, 0]
            image = batch["image"][i]
            # interior pixels only: every pixel within r (inside the frame) foreground; none: the whole mask
            r_hard = max(1, round(mask.shape[-1] / image.shape[-1]))
            pix = [rgb[:, y, x] for y, x in _interior(alpha >= 0.5, r_hard)]
            gt = [image[:, y, x] for y, x in _interior(mask >= 0.5, 1)]
            pred_colors.append(torch.stack(pix).mean(0) if pix else torch.full((3,), math.nan))
            gt_colors.append(torch.stack(gt).mean(0))
            both = (alpha >= 0.5) & (mask >= 0.5)
            M, S = both.shape[-1], image.shape[-1]
            both_small = torch.tensor([[bool(both[y * M // S, x * M // S]) for x in range(S)] for y in range(S)])
            pix = [rgb[:, y, x] for y, x in _interior(both, r_hard)] if both.any() else []
            gt = [image[:, y, x] for y, x in _interior(both_small, 1)] if both_small.any() else []
            pred_both.append(torch.stack(pix).mean(0) if pix else torch.full((3,), math.nan))
            gt_both.append(torch.stack(gt).mean(0) if gt else torch.full((3,), math.nan))
            groups.append(result.per_image[len(groups)]["group"])
    # each variant against the input colours of its own pixels, their mean as the one-colour prediction
    variants = (("", pred_colors, gt_colors), ("-overlap", pred_both, gt_both))
    for g in ("chair", "mug"):
        members = [i for i, x in enumerate(groups) if x == g]
        table = next(r for r in result.table if r["group"] == g)
        for suffix, preds, gts in variants:
            seen = [i for i in members if not torch.isnan(gts[i]).any()]
            assert seen, "the test needs reconstructions that overlap their masks"
            reference = torch.stack([gts[i] for i in seen]).mean(0)
            model_errors, base_errors = [], []
            for i in seen:
                row = result.per_image[i]
                want = (preds[i] - gts[i]).abs().mean().item()
                want_base = (reference - gts[i]).abs().mean().item()
                assert row[f"color-err{suffix}"] == pytest.approx(want, abs=1e-5)
                assert row[f"color-err-mean{suffix}"] == pytest.approx(want_base, abs=1e-5)
                model_errors.append(want)
                base_errors.append(want_base)
            ratio = sum(model_errors) / sum(base_errors)
            assert table[f"color-ratio{suffix}"] == pytest.approx(ratio, rel=1e-4)

    # shape: the baseline mesh scored with the metric function, the win decided per object
    batch = batches[0]
    direct = evaluate_meshes(
        (template * 0.9).expand(3, -1, -1), shapenet_model.template.faces, batch["points"], batch["normals"],
        num_points=400, icp_iterations=2,
    )  # fmt: skip
    for i in range(3):
        row = result.per_image[i]
        assert row["chamfer-L1-ICP-mean-shape"] == pytest.approx(float(direct["chamfer-L1-ICP"][i]), rel=1e-5)
        assert row["shape-win"] == (1.0 if row["chamfer-L1-ICP"] < row["chamfer-L1-ICP-mean-shape"] else 0.0)
    with pytest.raises(ValueError, match="shape_baseline"):
        evaluate(shapenet_model, data, EvalOptions("shapenet", **FAST), "synthetic", shape_baseline=template[:5])


def _varied_shapes(model):
    """A copy of ``model`` whose predicted shapes differ from image to image (random shape code and field)."""
    varied = copy.deepcopy(model)
    varied.set_active_dims(shape=varied.shape.code_dim)
    varied.set_stage_switches(deformation=True)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for layer, std in ((varied.shape.regressor[-1], 1.0), (varied.shape.field.mlp[-1], 0.05)):
            layer.weight.copy_(torch.randn(layer.weight.shape, generator=gen) * std)
    return varied


def test_own_mean_shape_against_a_direct_computation(shapenet_model, synth_root) -> None:
    model = _varied_shapes(shapenet_model)
    data = build_eval_dataset("synthetic", str(synth_root), "train", img_size=32)
    result = evaluate(model, data, EvalOptions("shapenet", own_mean_shape=True, **FAST), "synthetic")
    assert {"chamfer-L1-ICP-own-mean", "shape-win-own"} <= set(result.columns)

    # each group's mean of the predicted meshes, scored with each image's own predicted pose and alignment
    batches = [collate([data[i] for i in range(0, 3)]), collate([data[i] for i in range(3, len(data))])]
    with torch.no_grad():
        preds = [model.predict(b["image"]) for b in batches]
    groups = [row["group"] for row in result.per_image]
    verts = torch.cat([p.verts for p in preds])
    assert verts.std(0).max() > 1e-3  # the shapes do differ between images
    means = {g: verts[[i for i, x in enumerate(groups) if x == g]].mean(0) for g in set(groups)}
    start = 0
    for batch, pred in zip(batches, preds):
        n = len(batch["index"])
        own = torch.stack([means[groups[start + i]] for i in range(n)])
        direct = evaluate_meshes(
            own, model.template.faces, batch["points"], batch["normals"],
            R_pred=pred.R, T_pred=pred.T, R_gt=batch["R"], T_gt=batch["T"], num_points=400, icp_iterations=2,
        )  # fmt: skip
        for i in range(n):
            row = result.per_image[start + i]
            assert row["chamfer-L1-ICP-own-mean"] == pytest.approx(float(direct["chamfer-L1-ICP"][i]), rel=1e-4)
            assert row["shape-win-own"] == (1.0 if row["chamfer-L1-ICP"] < row["chamfer-L1-ICP-own-mean"] else 0.0)
        start += n


def test_own_mean_shape_of_a_one_shape_model_is_that_shape(shapenet_model, synth_root) -> None:
    # a model that outputs the same mesh for every image is its own mean: the two scores agree on every object
    data = build_eval_dataset("synthetic", str(synth_root), "train", img_size=32)
    one_shape = FixedShapeModel(shapenet_model, shapenet_model.template.verts * 0.8, pose="predicted")
    result = evaluate(one_shape, data, EvalOptions("shapenet", own_mean_shape=True, **FAST), "synthetic")
    for row in result.per_image:
        assert row["chamfer-L1-ICP-own-mean"] == pytest.approx(row["chamfer-L1-ICP"], rel=1e-4)
    # without ground-truth points (images protocol) the option changes nothing
    plain = evaluate(shapenet_model, data, EvalOptions("images", own_mean_shape=True, **FAST), "synthetic")
    assert "shape-win-own" not in plain.columns


SHAPE_COLUMNS = [f"shape-{m}{s}" for s in ("", "-gt", "-floor") for m in ("top1", "top3", "mrr")]


class _OneGroup(Dataset):
    """The items of a dataset as one group (no categories): here 2 objects x 2 views."""

    def __init__(self, data: Dataset) -> None:
        self.data = data

    def __len__(self) -> int:
        return len(self.data)

    def __getitem__(self, i: int) -> dict:
        return self.data[i]


def test_shape_retrieval_against_a_direct_computation(shapenet_model, synth_root) -> None:
    model = _varied_shapes(shapenet_model)
    data = _OneGroup(build_eval_dataset("synthetic", str(synth_root), "train", img_size=32))
    result = evaluate(model, data, EvalOptions("shapenet", shape_points=300, **FAST), "synthetic")
    assert set(SHAPE_COLUMNS) | {"shape-spread-ratio", "shape-detail-ratio"} <= set(result.columns)
    batch = collate([data[i] for i in range(len(data))])
    with torch.no_grad():
        pred = model.predict(batch["image"])
    faces = model.template.faces
    for group in ("synthetic",):
        rows = [i for i, r in enumerate(result.per_image) if r["group"] == group]
        objects = sorted({int(batch["model"][i]) for i in rows})
        assert len(objects) == 2 and len(rows) == 4  # two views of each object: two candidates
        # the candidates: the first 300 of a seeded permutation of each object's ground-truth points
        candidates = torch.stack(
            [
                batch["points"][i][torch.randperm(len(batch["points"][i]), generator=torch.Generator().manual_seed(o))]
                for o in objects
                for i in [next(j for j in rows if int(batch["model"][j]) == o)]
            ]
        )[:, :300].double()
        points = torch.stack([sample_points_from_meshes(pred.verts[i], faces, 300, seed=0)[0] for i in rows]).double()
        in_view = points @ pred.R[rows].double() + pred.T[rows, None].double()
        targets = torch.tensor([objects.index(int(batch["model"][i])) for i in rows])
        direct = shape_retrieval(in_view, batch["R"][rows], candidates, targets)
        for k, i in enumerate(rows):
            assert result.per_image[i]["shape-top1"] == pytest.approx(float(direct["top1"][k]))
            assert result.per_image[i]["shape-mrr"] == pytest.approx(float(direct["rr"][k]))
        assert 0 < next(r for r in result.table if r["group"] == group)["shape-spread-ratio"]
    # the retrieval alone: the same per-image scores, no spread
    alone = evaluate(model, data, EvalOptions("shapenet", shape_points=300, shape_spread=False, **FAST), "synthetic")
    assert not {"shape-spread-ratio", "shape-detail-ratio"} & set(alone.columns)
    for a, b in zip(alone.per_image, result.per_image, strict=True):
        assert {k: a[k] for k in SHAPE_COLUMNS} == {k: b[k] for k in SHAPE_COLUMNS}


def test_shape_retrieval_of_a_one_shape_model_is_its_floor(shapenet_model, synth_root) -> None:
    # one mesh for every image: its mean canonical mesh times its scale is itself, and its shapes do not spread
    data = _OneGroup(build_eval_dataset("synthetic", str(synth_root), "train", img_size=32))
    one_shape = FixedShapeModel(shapenet_model, shapenet_model.template.verts * 0.8, pose="predicted")
    result = evaluate(one_shape, data, EvalOptions("shapenet", shape_points=200, **FAST), "synthetic")
    assert "shape-top1" in result.columns
    for row in result.per_image:
        for m in ("top1", "top3", "mrr"):
            assert row[f"shape-{m}"] == row[f"shape-{m}-floor"]
    assert all(row["shape-spread-ratio"] == 0 and row["shape-detail-ratio"] == 0 for row in result.table)
    off = evaluate(one_shape, data, EvalOptions("shapenet", shape_points=0, **FAST), "synthetic")
    assert not {"shape-top1", "shape-spread-ratio"} & set(off.columns)
    # one object per category: nothing to retrieve it from
    per_category = evaluate(one_shape, data.data, EvalOptions("shapenet", shape_points=200, **FAST), "synthetic")
    assert "shape-top1" not in per_category.columns


def _loop_batches(data: Dataset, batch_size: int) -> list[dict]:
    """The batches the evaluation loop sees (predictions depend on the batch only through rounding)."""
    return [
        collate([data[i] for i in range(s, min(s + batch_size, len(data)))]) for s in range(0, len(data), batch_size)
    ]


def test_cub_protocol(real_model, cub_root) -> None:
    data = build_eval_dataset("cub_200", str(cub_root), "test", img_size=32)
    assert data[0]["mask"].shape[-1] == 256  # masks and keypoints in UNICORN's 256 px frame
    options = EvalOptions("cub", **FAST)
    result = evaluate(real_model, data, options, "cub_200")
    assert result.columns == [
        "mask-iou", "pck-5", "pck-10", "pck-15", "cand-share-min", "cand-share-max",
        "color-err", "color-err-mean", "color-ratio", "color-err-overlap", "color-err-mean-overlap",
        "color-ratio-overlap", "rec-mse",
    ]  # fmt: skip
    # the numbers are the metric functions' on the same predictions: mask IoU of the 3x3-supersampled silhouettes
    # at the masks' 256 px, PCK by keypoint transfer with the vertices seen in the 2x2-supersampled hard render
    verts, R, T, visible, keypoints, ious = [], [], [], [], [], []
    with torch.no_grad():
        for batch in _loop_batches(data, options.batch_size):
            pred = real_model.predict(batch["image"])
            hard = hard_render(real_model, pred.verts, pred.texture, pred.R, pred.T, 256, options.mask_supersample)
            ious += mask_iou(hard.images[:, 3:], batch["mask"], reduction="none").tolist()
            seen = hard_render(real_model, pred.verts, pred.texture, pred.R, pred.T, 256, 2)
            visible.append(vertex_visibility(seen.face_ids, real_model.template.faces, pred.verts.shape[1]))
            verts.append(pred.verts)
            R.append(pred.R)
            T.append(pred.T)
            keypoints.append(batch["keypoints"])
    assert [row["mask-iou"] for row in result.per_image] == pytest.approx(ious, abs=1e-6)
    camera = PerspectiveCamera(focal_length=float(real_model.renderer.camera.focal_length))
    pck = keypoint_transfer_pck(
        *(torch.cat(x) for x in (verts, R, T, visible, keypoints)), image_size=256, camera=camera, num_pairs=50
    )
    for key in ("pck-5", "pck-10", "pck-15"):
        assert result.mean[key] == pytest.approx(pck[key], abs=1e-9)
    assert 0 <= result.mean["pck-5"] <= result.mean["pck-10"] <= result.mean["pck-15"] <= 1


def test_p3d_protocol(real_model, p3d_root) -> None:
    data = build_eval_dataset("p3d_car", str(p3d_root), "test", img_size=32, max_images=2)
    result = evaluate(real_model, data, EvalOptions("p3d", **FAST), "p3d_car")
    # without ground-truth poses only the ICP-registered shape metrics mean something
    assert result.columns == [
        "chamfer-L1-ICP", "normal-cos-ICP", "iou-3d-ICP", "mask-iou", "cand-share-min", "cand-share-max",
        "color-err", "color-err-mean", "color-ratio", "color-err-overlap", "color-err-mean-overlap",
        "color-ratio-overlap", "rec-mse",
    ]  # fmt: skip
    # each image against its own CAD cloud, registered by ICP as the metric function does (the fixture's clouds
    # have one size: stacked, they are scored as one batch, with one draw of surface samples)
    (batch,) = _loop_batches(data, FAST["batch_size"])
    with torch.no_grad():
        pred = real_model.predict(batch["image"])
    direct = evaluate_meshes(
        pred.verts, real_model.template.faces, batch["points"], batch.get("normals"),
        num_points=400, icp_iterations=2, run_direct=False,
    )  # fmt: skip
    for i, row in enumerate(result.per_image):
        for key in ("chamfer-L1-ICP", "normal-cos-ICP", "iou-3d-ICP"):
            assert row[key] == pytest.approx(float(direct[key][i]), rel=1e-5, abs=1e-12)


def test_images_protocol_and_max_images(real_model, synth_root) -> None:
    data = build_eval_dataset("folder", str(synth_root), "test", img_size=32, max_images=3)
    assert len(data) == 3
    result = evaluate(real_model, data, EvalOptions("images", **FAST), "folder")
    assert result.columns == ["cand-share-min", "cand-share-max", "rec-mse"] and result.table[0]["group"] == "folder"
    # the reconstruction error: the model's render at its predicted pose against the input
    (batch,) = _loop_batches(data, FAST["batch_size"])
    with torch.no_grad():
        pred = real_model.predict(batch["image"])
        rec, _ = real_model.render(pred.verts, pred.texture, pred.R, pred.T, pred.background)
    mse = (rec - batch["image"]).square().mean(dim=(1, 2, 3))
    assert [row["rec-mse"] for row in result.per_image] == pytest.approx(mse.tolist(), rel=1e-5)


def test_items_without_an_index_are_numbered_in_order(real_model) -> None:
    """A dataset of another library (items without ``index``) is scored, its rows numbered by position."""
    images = torch.rand(4, 3, 32, 32, generator=torch.Generator().manual_seed(3))
    data = [{"image": image} for image in images]
    result = evaluate(real_model, data, EvalOptions("images", report_samples=2, **FAST), "mine")
    assert [row["index"] for row in result.per_image] == [0, 1, 2, 3]
    assert [s.index for s in result.samples] == [0, 1] and result.table[0]["group"] == "mine"
    with torch.no_grad():
        pred = real_model.predict(images)
        rec, _ = real_model.render(pred.verts, pred.texture, pred.R, pred.T, pred.background)
    mse = (rec - images).square().mean(dim=(1, 2, 3))
    assert [row["rec-mse"] for row in result.per_image] == pytest.approx(mse.tolist(), rel=1e-5)


def test_helpers_and_validation() -> None:
    assert (
        spread_indices(10, 3) == [0, 4, 9] and spread_indices(3, None) == [0, 1, 2] and spread_indices(2, 5) == [0, 1]
    )
    batch = collate([{"a": torch.zeros(2), "p": torch.zeros(3, 3)}, {"a": torch.ones(2), "p": torch.zeros(5, 3)}])
    assert batch["a"].shape == (2, 2) and isinstance(batch["p"], list)
    assert protocol_for("cub_200") == "cub"
    with pytest.raises(ValueError, match="unknown dataset"):
        protocol_for("imagenet")
    with pytest.raises(ValueError, match="protocol"):
        EvalOptions("nope")
    with pytest.raises(ValueError, match="num_points"):
        EvalOptions("shapenet", num_points=0)
    for workers in (0, -2):  # scipy's k-d trees refuse them in the middle of an evaluation
        with pytest.raises(ValueError, match=r"^nn_workers must be None, -1 \(all cores\) or >= 1, got -?\d$"):
            EvalOptions("shapenet", nn_workers=workers)
    assert EvalOptions("shapenet", nn_workers=-1).nn_workers == -1


POSE_METRICS = {"rot-err-mean", "rot-err-median", "rot-acc-30", "azim-err-mean", "azim-err-median"}


def test_oracle_pose_scores_the_shape_at_the_ground_truth_pose(shapenet_model, synth_root) -> None:
    data = build_eval_dataset("synthetic", str(synth_root), "train", img_size=32)
    result = evaluate(shapenet_model, data, EvalOptions("shapenet", oracle_pose=True, **FAST), "synthetic")
    # pose errors would be trivially 0 and no candidate is selected: both are left out
    assert not (POSE_METRICS | {"cand-share-min", "cand-share-max"}) & set(result.columns)
    assert result.candidate_shares == {} and all("candidate" not in row for row in result.per_image)
    assert {"chamfer-L1", "mask-iou", "rec-mse"} <= set(result.columns)

    # independently: the metric functions with the ground-truth pose in place of the prediction
    batch = collate([data[i] for i in range(3)])  # the loop's first batch
    with torch.no_grad():
        pred = shapenet_model.predict(batch["image"])
        hard = hard_render(shapenet_model, pred.verts, pred.texture, batch["R"], batch["T"], 32, supersample=3)
    R, T = batch["R"], batch["T"]
    direct = evaluate_meshes(
        pred.verts, shapenet_model.template.faces, batch["points"], batch["normals"],
        R_pred=R, T_pred=T, R_gt=R, T_gt=T, num_points=400, icp_iterations=2,
    )  # fmt: skip
    iou = mask_iou(hard.images[:, 3:], batch["mask"], reduction="none")
    for i in range(3):
        assert result.per_image[i]["chamfer-L1"] == pytest.approx(float(direct["chamfer-L1"][i]), rel=1e-5)
        assert result.per_image[i]["iou-3d"] == pytest.approx(float(direct["iou-3d"][i]), abs=1e-12)
        assert 0 <= result.per_image[i]["iou-3d-ICP"] <= 1
        assert result.per_image[i]["mask-iou"] == pytest.approx(float(iou[i]), abs=1e-6)
    assert torch.equal(result.samples[0].R, R[0])  # the report shows the pose it was scored at

    # the predicted pose differs from the ground truth, and so do the scores
    predicted = evaluate(shapenet_model, data, EvalOptions("shapenet", **FAST), "synthetic")
    assert predicted.per_image[0]["chamfer-L1"] != pytest.approx(result.per_image[0]["chamfer-L1"], rel=1e-3)


class _NoPose(Dataset):
    """Items of another dataset with their ground-truth pose marked missing."""

    def __init__(self, data: Dataset) -> None:
        self.data = data

    def __len__(self) -> int:
        return 2

    def __getitem__(self, i: int) -> dict:
        return {**self.data[i], "has_pose": torch.tensor(False)}


def test_oracle_pose_validation(shapenet_model, synth_root) -> None:
    for protocol in ("cub", "p3d", "images"):
        with pytest.raises(ValueError, match="oracle_pose needs the 'shapenet' protocol"):
            EvalOptions(protocol, oracle_pose=True)
    data = _NoPose(build_eval_dataset("synthetic", str(synth_root), "train", img_size=32))
    with pytest.raises(ValueError, match=r"ground-truth pose for every item; items \[0, 1\]"):
        evaluate(shapenet_model, data, EvalOptions("shapenet", oracle_pose=True, **FAST))


def test_candidate_usage(shapenet_model, synth_root) -> None:
    data = build_eval_dataset("synthetic", str(synth_root), "train", img_size=32)
    result = evaluate(shapenet_model, data, EvalOptions("shapenet", **FAST), "synthetic")
    items = collate([data[i] for i in range(len(data))])
    with torch.no_grad():
        poses = shapenet_model.predict(items["image"]).poses
    probs = poses.probs  # (K, B)
    K = shapenet_model.n_candidates
    assert probs.shape[0] == K == 6
    assert [row["candidate"] for row in result.per_image] == probs.argmax(0).tolist()
    assert set(result.candidate_shares) == {"chair", "mug"}
    for row in result.table[:-1]:
        chosen = [r["candidate"] for r in result.per_image if r["group"] == row["group"]]
        shares = result.candidate_shares[row["group"]]
        assert shares == pytest.approx([chosen.count(k) / len(chosen) for k in range(K)])
        assert sum(shares) == pytest.approx(1.0)
        # 2 images per group over 6 candidates: at least 4 candidates are never chosen
        assert row["cand-share-min"] == 0.0 and row["cand-share-max"] == max(shares) >= 0.5
    # rot-acc-30-any: some candidate within 30 degrees, in the frame aligned on the selected candidates (a loop)
    for row in result.table[:-1]:
        idx = [i for i, r in enumerate(result.per_image) if r["group"] == row["group"]]
        chosen = [poses.R[probs[:, i].argmax(), i] for i in idx]
        Q = align_canonical_frame(torch.stack(chosen), items["R"][idx])
        hits = [any(geodesic_error(Q @ poses.R[k, i], items["R"][i]) < 30 for k in range(K)) for i in idx]
        assert row["rot-acc-30-any"] == pytest.approx(sum(hits) / len(hits))
        assert row["rot-acc-30-any"] >= row["rot-acc-30"]
    # the per-image candidate index is not a metric: never averaged into the table
    assert "candidate" not in result.columns and all("candidate" not in row for row in result.table)
    order = [result.columns.index(c) for c in ("rot-acc-30", "cand-share-min", "cand-share-max", "rec-mse")]
    assert order == sorted(order)


def test_candidate_shares_helper() -> None:
    assert candidate_shares([0, 0, 2, 0], 4) == [0.75, 0.0, 0.25, 0.0]
    assert candidate_shares([1], 2) == [0.0, 1.0]
    with pytest.raises(ValueError, match="in \\[0, 3\\)"):
        candidate_shares([0, 3], 3)
    with pytest.raises(ValueError, match="no images"):
        candidate_shares([], 3)
    with pytest.raises(ValueError, match="at least one candidate"):
        candidate_shares([0], 0)


def test_protocol_registry_says_what_each_protocol_scores() -> None:
    from unicorn.data.registry import DATASETS
    from unicorn.evaluation import PROTOCOL_REGISTRY, get_protocol
    from unicorn.registry import UnknownNameError

    assert {spec.protocol for _, spec in DATASETS.items()} == set(PROTOCOL_REGISTRY)
    shapenet, cub, p3d, images = (get_protocol(n) for n in ("shapenet", "cub", "p3d", "images"))
    assert shapenet.meshes == "posed" and shapenet.poses and shapenet.training_clouds
    assert p3d.meshes == "icp" and not p3d.poses and cub.keypoints and not images.masks
    with pytest.raises(
        UnknownNameError, match=r"unknown protocol 'kitti'; known: \['cub', 'images', 'p3d', 'shapenet'\]"
    ):
        EvalOptions(protocol="kitti")
    with pytest.raises(ValueError, match="oracle_pose needs"):
        EvalOptions(protocol="p3d", oracle_pose=True)


def test_overflow_note_says_the_share_once_per_block(caplog) -> None:
    import warnings

    from unicorn.evaluation.session import overflow_note
    from unicorn.render import rasterize_meshes

    # four triangles at depths 1-4, each covering the whole 16 x 16 image: with K = 2 every pixel overflows
    tri = torch.tensor([[-9.0, -9.0], [9.0, -9.0], [0.0, 9.0]])
    verts = torch.cat([torch.cat([tri, torch.full((3, 1), z)], 1) for z in (1.0, 2.0, 3.0, 4.0)])[None]
    faces = torch.arange(12).reshape(4, 3)
    with caplog.at_level("INFO", logger="unicorn.evaluation.session"), warnings.catch_warnings():
        warnings.simplefilter("error")  # the renders in the block do not warn by themselves
        with overflow_note("unicorn-eval"):
            for _ in range(3):
                rasterize_meshes(verts, faces, 16, 0.0, 2)
                rasterize_meshes(verts, faces, 16, 0.0, 1)  # another setting: counted apart
            rasterize_meshes(verts, faces, 16, 0.0, 8)  # no overflow with this setting: not in the share
        with overflow_note("unicorn-reconstruct"):
            rasterize_meshes(verts, faces, 16, 0.0, 8)  # nothing to say
        with pytest.raises(RuntimeError), overflow_note("unicorn-reconstruct"):
            rasterize_meshes(verts, faces, 16, 0.0, 2)
            raise RuntimeError("the command failed: its error is what matters")
    notes = [r.getMessage() for r in caplog.records if "faces_per_pixel" in r.getMessage()]
    assert notes == [
        "note: unicorn-eval: 100% of the 768 pixels rendered with faces_per_pixel=1 had more candidate faces within "
        "the blur radius, and lost their farthest ones; 100% of the 768 pixels rendered with faces_per_pixel=2 had "
        "more candidate faces within the blur radius, and lost their farthest ones (faces_per_pixel is the "
        "checkpoint's renderer setting: renderer.faces_per_pixel in training)"
    ]


@pytest.mark.parametrize("split", ["val", "test"])
def test_pascal3d_is_evaluated_against_its_cad_clouds_on_every_split(p3d_root, split) -> None:
    data = build_eval_dataset("p3d_car", str(p3d_root), split, img_size=32)
    item = data[0]
    assert item["points"].shape[-1] == 3 and item["points"].shape[0] > 0, sorted(item)
