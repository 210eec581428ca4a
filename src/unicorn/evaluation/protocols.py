"""The evaluation protocols and the records of an evaluation: options, per-image samples, results.

Protocols (UNICORN's, see ``docs/evaluation.md`` and :mod:`unicorn.metrics`):

- ``"shapenet"`` (``shapenet_nmr``, ``synthetic``): one fixed random view per test model. Per image:
  ``chamfer-L1`` / ``normal-cos`` after mapping the prediction into the ground-truth object frame with the
  predicted and ground-truth poses, ``chamfer-L1-ICP`` / ``normal-cos-ICP`` after unit-cube normalisation and the
  anisotropic-scale gradient ICP (:func:`~unicorn.metrics.evaluate_meshes`), ``iou-3d`` / ``iou-3d-ICP`` (3D IoU
  at 32^3 under the same two alignments, see below), ``mask-iou`` of the hard-rendered silhouette (3 x 3 samples
  per pixel, the pixels more than half covered, see ``EvalOptions.mask_supersample``).
  Per category: pose errors (:func:`~unicorn.metrics.pose_errors`, after aligning the learned canonical frame to
  the ground truth with one rotation; NaN for a category of one image, which that rotation aligns exactly).
  Categories are averaged, then the categories.
- ``"cub"`` (``cub_200``): ``mask-iou`` per image with masks at 256 px, and PCK by keypoint transfer over image
  pairs (:func:`~unicorn.metrics.keypoint_transfer_pck`), the visible vertices being those of faces hit by the 2x
  supersampled hard rasterisation (512 px for the 256 px keypoint frame).
- ``"p3d"`` (``p3d_car``): ``chamfer-L1-ICP`` / ``normal-cos-ICP`` / ``iou-3d-ICP`` against the CAD point clouds
  (there is no ground-truth pose, so no GT-pose alignment) and ``mask-iou``.
- ``"images"`` (``compcars``, ``lsun``, ``folder``): no ground truth, the reconstruction error only.

3D IoU (``iou-3d``, ``iou-3d-ICP``; :func:`~unicorn.metrics.voxels.point_cloud_voxel_iou`): the predicted surface
samples of the Chamfer distance, after its alignment, and the ground-truth point cloud are each voxelised solid
on the 32^3 grid of the unit cube [-0.5, 0.5]^3 (extended where a prediction sticks out): the cells holding a
point, closed by one cell (dilated, holes filled, eroded); IoU = cells of both / cells of either. The classic
Pascal3D+ protocol (CMR, DRC) also voxelises surfaces at 32^3 and fills them, but places all predictions with one
translation and scale for the whole test set; the per-object ICP here (rotation, translation, anisotropic scale)
fits each prediction better, so the numbers are not comparable with that table.

Every protocol also reports ``rec-mse``, the mean squared error of the model's own rendering (with its predicted
background) against the input, the quantity the model was trained to lower.

Instance-level metrics (:mod:`unicorn.metrics.instance`) tell a model that reconstructs each object from one that
outputs the category mean:

- colour (every protocol with ground-truth masks): per image ``color-err``, the L1 distance (mean over RGB)
  between the mean foreground colour of the hard-rendered reconstruction (inside its silhouette) and of the
  input (inside its mask), both over the interior pixels (each mask eroded by one input pixel: a border pixel
  mixes object and background, and its colour depends on where each silhouette runs), and ``color-err-mean``,
  the same for a predictor of one colour for every image (the average input foreground colour of the group's
  evaluated images); per group ``color-ratio``, the ratio of their means (below 1 only when reconstructions
  carry their image's colour); and the same three over the pixels both the reconstruction's silhouette and the
  input's mask cover, ``color-err-overlap``, ``color-err-mean-overlap`` and ``color-ratio-overlap``: the texture's
  colour alone, where ``color-ratio`` also counts what a wrong silhouette paints (a genus-0 mesh covering the
  open frame of a chair back paints it; the input shows the background there);
- shape (with ``shape_baseline``, a mean shape, one mesh or one per group, see :func:`evaluate`): per image
  ``chamfer-L1-ICP-mean-shape``, Chamfer-L1 after ICP of its group's mesh on the same object, and ``shape-win``, 1
  where the model's ``chamfer-L1-ICP`` is lower (0.5 on a tie), whose group mean is the share of objects the model
  wins;
- own shape (``EvalOptions(own_mean_shape=True)``): per image ``chamfer-L1-ICP-own-mean``, the same score for
  the model's *own* average shape (the mean of its predicted meshes over the group's evaluated images, vertex by
  vertex on the template topology) placed with the image's predicted pose, and ``shape-win-own``, 1 where the
  model's own prediction is closer. The mean-shape baseline above is fitted to the 3D ground truth, so it mixes
  two questions (is the category shape accurate? is each shape the image's?); this one asks only the second:
  a model that outputs one shape for every image ties its own mean (win share 0.5 from ties), one whose
  per-image shapes follow the objects wins on most of them;
- shape identity (``EvalOptions.shape_points`` > 0, protocols with ground-truth points and poses, items that
  name their object, ``model``): per image ``shape-top1`` / ``shape-top3`` / ``shape-mrr``, whether the image's
  object is the closest / among the 3 closest / at which rank (reciprocal) among the group's evaluated objects
  (distinct objects: several views of one object make one candidate), from its reconstruction
  (:func:`~unicorn.metrics.shape_retrieval`): the predicted mesh at its pose, in view coordinates, against each
  object's ground truth seen in the image's view (its ground-truth pose), both normalised for the size that one
  image cannot know (centred, unit RMS radius: proportions are kept) and compared by Chamfer-L1. Chance is
  ``1 / C`` and ``3 / C`` for C objects. Beside it, through the same measure, its ceiling ``shape-*-gt`` (a
  sample of the image's ground-truth surface independent of the candidates') and its floor ``shape-*-floor`` (the
  model's mean canonical mesh over the group's images times the image's predicted scale, at the same pose: what
  the scale alone identifies). Per group ``shape-spread-ratio``, how much the predicted shapes differ over how
  much the ground-truth shapes do (:func:`~unicorn.metrics.shape_spread`: the mean Chamfer-L1 between two
  normalised shapes of different objects): 0 for a model emitting one shape, near 1 when the predicted shapes
  vary as the objects do; ``shape-detail-ratio``, the same with each shape normalised along each axis (the
  predicted meshes in their canonical frame, whose axes the anisotropic scale stretches): what varies beyond the
  proportions, 0 for a model emitting one shape stretched by a per-image scale;
- pose: ``rot-acc-30`` and, separately, ``rot-flip-150``, the share of images predicted turned round; each
  image's own error after the alignment is kept in its row (``rot-err``, degrees), so that one can see, e.g.,
  whether the flipped views are whole objects turned round or scattered views. For models with K > 1 candidates,
  ``rot-acc-30-any``: the share of images for which some candidate is within 30 degrees (the frame aligned on the
  selected ones), the accuracy of a perfect choice among the candidates. Well above ``rot-acc-30``, the error is
  the choice (the probabilities); near it, the candidates themselves.

Two diagnostics complete them:

- pose-candidate usage: per image the index of the selected candidate (``candidate`` in the per-image rows) and,
  per group, ``cand-share-min`` / ``cand-share-max``, the smallest and largest fraction of the group's images
  that chose one candidate (a candidate never chosen counts as 0). A collapsed pose head (every image on one or
  two candidates) shows as ``cand-share-min`` 0 and a large ``cand-share-max``; a balanced one as both near
  ``1 / K``. Only for models with K > 1 candidates.
- ``EvalOptions(oracle_pose=True)`` (``"shapenet"`` only): the reconstructions, the hard masks and the GT-pose
  alignment of the meshes use the ground-truth pose instead of the predicted one, so that ``chamfer-L1`` and
  ``mask-iou`` measure the shape alone; the pose errors and the candidate usage are then left out.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch

from unicorn.config.schema import EVAL_BATCH_SIZE, FINAL_EVAL, REPORT_SAMPLES, SHAPE_POINTS
from unicorn.data.registry import dataset_spec
from unicorn.evaluation.columns import COLOR_INTERIOR, COLOR_SUFFIXES, METRIC_HELP, METRIC_ORDER, METRICS, ROW_INFO
from unicorn.metrics.sampling import check_point_count
from unicorn.model.ranges import check_ranges, ranged
from unicorn.registry import Registry

__all__ = [
    "COLOR_INTERIOR",
    "COLOR_SUFFIXES",
    "METRICS",
    "METRIC_HELP",
    "METRIC_ORDER",
    "PROTOCOL_REGISTRY",
    "ROW_INFO",
    "EvalOptions",
    "EvaluationResult",
    "Protocol",
    "Sample",
    "get_protocol",
    "protocol_for",
]


@dataclass(frozen=True)
class Protocol:
    """What one evaluation protocol scores (the registry :data:`PROTOCOL_REGISTRY`, see the module docstring).

    Attributes:
        name: its name, as the datasets' entries name it (:data:`unicorn.data.registry.DATASETS`).
        masks: ground-truth masks: ``mask-iou`` and the colour metrics.
        meshes: ground-truth point clouds: ``"posed"`` (Chamfer with the ground-truth pose and after ICP),
            ``"icp"`` (after ICP only: no ground-truth pose), or None.
        poses: ground-truth poses: rotation errors after the canonical-frame alignment; ``oracle_pose`` allowed.
        keypoints: PCK by keypoint transfer.
        training_clouds: the dataset has training point clouds (a mean-shape baseline can be fitted).
        template_level: the icosphere level of the mesh the protocol scores, when it is not the model's own
            (``unicorn-eval`` rebuilds the template at it unless ``--template-level`` says otherwise), or None.
    """

    name: str
    masks: bool = False
    meshes: str | None = None
    poses: bool = False
    keypoints: bool = False
    training_clouds: bool = False
    template_level: int | None = None


#: every protocol by name
PROTOCOL_REGISTRY: Registry[Protocol] = Registry("protocol")
for _protocol in (
    Protocol("shapenet", masks=True, meshes="posed", poses=True, training_clouds=True),
    Protocol("cub", masks=True, keypoints=True, template_level=4),  # UNICORN's kp_eval.py: the level-4 mesh
    Protocol("p3d", masks=True, meshes="icp"),
    Protocol("images"),
):
    PROTOCOL_REGISTRY.add(_protocol.name, _protocol)


def get_protocol(name: str) -> Protocol:
    """The protocol of that name.

    Raises:
        unicorn.registry.UnknownNameError: an unknown name (the known ones are listed).
    """
    return PROTOCOL_REGISTRY.get(name)


def protocol_for(dataset_name: str) -> str:
    """The evaluation protocol of a dataset name (its entry in :data:`unicorn.data.registry.DATASETS`)."""
    return dataset_spec(dataset_name).protocol


@dataclass
class EvalOptions:
    """Settings of an evaluation run.

    Attributes:
        protocol: ``"shapenet"``, ``"cub"``, ``"p3d"`` or ``"images"``.
        batch_size: images per forward pass.
        num_points: points sampled on each predicted mesh (UNICORN: 100k).
        icp_iterations: ICP iterations (UNICORN: 100); 0 skips the ``-ICP`` metrics.
        mask_supersample: samples per pixel side of the hard renders scored against ground-truth masks (IoU,
            colours); a pixel is in the silhouette when more than half of its samples hit. Odd, so that no pixel
            is exactly half covered (with 2 x 2 samples a half-covered pixel averages 0.5 and drops out, which
            shrinks silhouettes: ``docs/evaluation.md``, "Masks and keypoints"); 3 is also how the synthetic
            masks are made (3 x 3 rays per pixel).
        visibility_supersample: supersampling of the hard render whose faces make the visible vertices of the
            keypoint transfer (UNICORN: 2).
        num_pairs: keypoint-transfer pairs (UNICORN: 10,000); N images forming at most that many ordered pairs
            use each ordered pair once (:func:`~unicorn.metrics.keypoint_transfer_pck`).
        align_pose: align the learned canonical frame to the ground truth before the pose errors.
        average_texture: predict mean-colour textures (for checkpoints still in that training phase).
        report_samples: images kept (on CPU) for the visual report.
        num_workers: DataLoader workers.
        nn_workers: threads of the nearest-neighbour queries of scipy's k-d trees, the backend where pykdtree is
            not installed (pykdtree's use ``OMP_NUM_THREADS`` threads); -1: all cores; None: torch's thread count
            (exact search: the results do not depend on it).
        seed: seed of the point sampling.
        progress: show a progress bar.
        progress_label: the bar's label (default ``eval <dataset name>``).
        progress_leave: keep the finished bar on screen (False: erase it, for bars inside another one's).
        oracle_pose: protocols with ground-truth poses (``"shapenet"``) only: render the reconstructions and
            masks, and align the meshes, with the ground-truth pose instead of the predicted one, so that
            ``chamfer-L1`` and ``mask-iou`` score the shape alone; the pose errors (trivially 0) and the
            candidate usage are left out. Every item must have a ground-truth pose.
        own_mean_shape: also score, per image, the model's own average shape over the group's evaluated images
            (``chamfer-L1-ICP-own-mean``, ``shape-win-own``; only with ground-truth points and ICP, otherwise
            ignored). Costs one more forward pass over the dataset and doubles the Chamfer work.
        shape_points: points per shape of the shape retrieval (``shape-top1`` ..., ``shape-spread-ratio``); 0: off.
            It costs ``3 Q C + 4 Q^2`` Chamfer distances between clouds of this size per group of Q images of C
            objects (retrieval of three reconstructions, two spreads of the predicted and ground-truth shapes), so
            it grows with the square of the group's size: meant for sets of tens to a few hundred images.
        shape_spread: with ``shape_points``, also each group's ``shape-spread-ratio`` and ``shape-detail-ratio``
            (the ``4 Q^2`` above); False scores the retrieval alone, whose cost grows with ``Q C``: every view of a
            test set.
    """

    protocol: str = "shapenet"
    batch_size: int = ranged(EVAL_BATCH_SIZE, 1)
    num_points: int = ranged(FINAL_EVAL["num_points"], 1)
    icp_iterations: int = ranged(FINAL_EVAL["icp_iterations"], 0)
    mask_supersample: int = ranged(3, 1)
    visibility_supersample: int = ranged(2, 1)
    num_pairs: int = ranged(10_000, 1)
    align_pose: bool = True
    average_texture: bool = False
    report_samples: int = ranged(REPORT_SAMPLES, 0)
    num_workers: int = ranged(0, 0)
    nn_workers: int | None = None
    seed: int = 0
    progress: bool = True
    progress_label: str | None = None
    progress_leave: bool = True
    oracle_pose: bool = False
    own_mean_shape: bool = False
    shape_points: int = ranged(SHAPE_POINTS, 0)
    shape_spread: bool = True

    def __post_init__(self) -> None:
        protocol = get_protocol(self.protocol)
        check_ranges(vars(self), EvalOptions)
        check_point_count(f"num_points={self.num_points}", self.num_points)
        check_point_count(f"shape_points={self.shape_points}", self.shape_points)
        if self.nn_workers is not None and not (self.nn_workers == -1 or self.nn_workers >= 1):
            raise ValueError(f"nn_workers must be None, -1 (all cores) or >= 1, got {self.nn_workers}")
        if self.oracle_pose and not protocol.poses:
            # the other protocols have no ground-truth pose to substitute
            raise ValueError(f"oracle_pose needs the 'shapenet' protocol (ground-truth poses), got {self.protocol!r}")


@dataclass
class Sample:
    """One evaluated image kept for the report (CPU tensors).

    Attributes:
        index: dataset index.
        group: its group (category) name.
        image: (3, S, S) model input.
        reconstruction: (3, S, S) the model's rendering over its predicted background.
        alpha: (1, M, M) hard-rendered predicted silhouette (M = ground-truth mask size, or S).
        mask: (1, M, M) ground-truth mask, or None.
        verts: (V, 3) predicted object-frame mesh; texture: (3, Ht, Wt).
        R: (3, 3); T: (3,) the pose it was rendered with: the predicted one, or the ground truth with
            ``oracle_pose``.
        scores: this image's per-image metrics (and ``candidate``, the selected pose candidate, when recorded).
    """

    index: int
    group: str
    image: torch.Tensor
    reconstruction: torch.Tensor
    alpha: torch.Tensor
    mask: torch.Tensor | None
    verts: torch.Tensor
    texture: torch.Tensor
    R: torch.Tensor
    T: torch.Tensor
    scores: dict[str, float] = field(default_factory=dict)


@dataclass
class EvaluationResult:
    """Output of :func:`evaluate`.

    Attributes:
        protocol: the protocol used.
        per_image: one dict per image: ``index``, ``group``, ``candidate`` (int index of the selected pose
            candidate, when recorded, see :func:`evaluate`) and its metrics.
        table: one row per group then a ``mean`` row (mean over groups): ``group``, ``n-images`` and metrics.
        columns: the metric columns of ``table``, in display order.
        samples: images kept for the report.
        seconds: wall-clock time of the evaluation.
        candidate_shares: group -> the K fractions of its images that selected each pose candidate (summing to
            1); empty when not recorded (one candidate, or ``oracle_pose``).
    """

    protocol: str
    per_image: list[dict[str, Any]]
    table: list[dict[str, Any]]
    columns: list[str]
    samples: list[Sample]
    seconds: float
    candidate_shares: dict[str, list[float]] = field(default_factory=dict)

    @property
    def mean(self) -> dict[str, Any]:
        """The ``mean`` row of the table."""
        return self.table[-1]
