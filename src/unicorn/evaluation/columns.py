"""The columns of an evaluation's tables: every metric, which way is better and what it means (the report shows
both), and the per-image entries that are not averaged. What each protocol scores: :mod:`unicorn.evaluation.protocols`.
"""

from __future__ import annotations

__all__ = ["COLOR_INTERIOR", "COLOR_SUFFIXES", "METRICS", "METRIC_HELP", "METRIC_ORDER", "ROW_INFO"]

#: colour metrics leave out this many border pixels (input resolution) of each mask: there silhouettes differ and
#: colours mix with the background (why one: ``docs/evaluation.md``, "Instance columns")
COLOR_INTERIOR = 1
#: the colour columns' variants: "" each image inside its own silhouette, "-overlap" inside the pixels both cover
COLOR_SUFFIXES = ("", "-overlap")

#: every metric column, in table order: which way is better and what it means (the report shows both)
METRICS: dict[str, tuple[str, str]] = {
    "n-images": ("", "number of evaluated images"),
    "chamfer-L1": (
        "lower",
        "Chamfer-L1 x10 between the predicted mesh, placed in the ground-truth object frame through the "
        "predicted and ground-truth cameras, and the ground-truth points",
    ),
    "chamfer-L1-ICP": (
        "lower",
        "Chamfer-L1 x10 after normalising the prediction to the unit cube and registering it with "
        "gradient ICP (rotation, translation, anisotropic scale)",
    ),
    "normal-cos": ("higher", "mean |cos| between matched normals, GT-pose aligned"),
    "normal-cos-ICP": ("higher", "mean |cos| between matched normals, after ICP"),
    "iou-3d": (
        "higher",
        "3D IoU of the GT-pose aligned prediction and the ground-truth points, both voxelised solid at 32^3 over "
        "the unit cube (cells holding surface points, closed by one cell, holes filled)",
    ),
    "iou-3d-ICP": ("higher", "3D IoU after the normalisation and ICP of chamfer-L1-ICP"),
    "mask-iou": ("higher", "IoU of the hard-rendered predicted silhouette with the ground-truth mask"),
    "pck-5": ("higher", "keypoints transferred between image pairs through the meshes within 5% of the image side"),
    "pck-10": ("higher", "... within 10% of the image side"),
    "pck-15": ("higher", "... within 15% of the image side"),
    "rot-err-mean": (
        "lower",
        "mean geodesic camera rotation error (degrees), learned canonical frame aligned to the GT",
    ),
    "rot-err-median": ("lower", "median geodesic camera rotation error (degrees)"),
    "rot-acc-30": ("higher", "fraction of images with a rotation error below 30 degrees"),
    "rot-flip-150": ("lower", "fraction of images with a rotation error above 150 degrees (predicted turned round)"),
    "rot-acc-30-any": (
        "higher",
        "fraction of images with some pose candidate within 30 degrees (same alignment): rot-acc-30 if the most "
        "likely candidate were always the best one",
    ),
    "azim-err-mean": ("lower", "mean camera azimuth error (degrees)"),
    "azim-err-median": ("lower", "median camera azimuth error (degrees)"),
    "cand-share-min": (
        "higher",
        "smallest fraction of the group's images that chose one pose candidate (0: a candidate never chosen)",
    ),
    "cand-share-max": ("lower", "largest fraction of the group's images that chose one pose candidate"),
    "color-err": (
        "lower",
        "L1 between the mean colours of the reconstruction and of the input over the mask interiors",
    ),
    "color-err-mean": ("lower", "the same for the group's average input colour predicted for every image"),
    "color-ratio": (
        "lower",
        "color-err / color-err-mean over the group: below 1 only when reconstructions carry their image's colour",
    ),
    "color-err-overlap": (
        "lower",
        "color-err over the interior of the pixels both the reconstruction and the input mask cover",
    ),
    "color-err-mean-overlap": ("lower", "color-err-mean over the same pixels"),
    "color-ratio-overlap": (
        "lower",
        "color-err-overlap / color-err-mean-overlap: the texture's colour alone, without what the reconstruction "
        "paints outside the object or leaves out of it",
    ),
    "chamfer-L1-ICP-mean-shape": (
        "lower",
        "Chamfer-L1 x10 after ICP of the object's category's mean training shape on the same object",
    ),
    "shape-win": (
        "higher",
        "share of objects on which the model's chamfer-L1-ICP beats the mean shape's (0.5 for a tie)",
    ),
    "chamfer-L1-ICP-own-mean": (
        "lower",
        "Chamfer-L1 x10 after ICP of the model's own average shape at the image's predicted pose",
    ),
    "shape-win-own": (
        "higher",
        "share of objects on which the model's own prediction beats its own average shape (0.5: one shape for all)",
    ),
    "shape-top1": (
        "higher",
        "share of images whose object is the closest of the group's objects to the reconstruction (normalised "
        "Chamfer-L1 in the image's view; chance 1 / objects)",
    ),
    "shape-top3": ("higher", "... among the 3 closest (chance 3 / objects)"),
    "shape-mrr": ("higher", "mean reciprocal rank of the image's object among the group's objects"),
    "shape-top1-gt": ("higher", "shape-top1 of a ground-truth surface sample: the ceiling of the measure"),
    "shape-top3-gt": ("higher", "shape-top3 of a ground-truth surface sample"),
    "shape-mrr-gt": ("higher", "shape-mrr of a ground-truth surface sample"),
    "shape-top1-floor": (
        "higher",
        "shape-top1 of the model's mean canonical mesh times the image's predicted scale: what the scale alone gives",
    ),
    "shape-top3-floor": ("higher", "shape-top3 of the mean canonical mesh times the image's scale"),
    "shape-mrr-floor": ("higher", "shape-mrr of the mean canonical mesh times the image's scale"),
    "shape-spread-ratio": (
        "higher",
        "mean normalised Chamfer-L1 between the predicted shapes of two objects over the same for the ground "
        "truth (0: one shape for all)",
    ),
    "shape-detail-ratio": (
        "higher",
        "the same with each shape scaled to a unit RMS along each axis: the spread beyond the proportions "
        "(0: one shape for all, anisotropically scaled)",
    ),
    "rec-mse": ("lower", "mean squared error of the model's rendering (with its background) against the input"),
}
#: column order of the tables; "lower" / "higher" says which way is better
METRIC_ORDER = {name: better for name, (better, _) in METRICS.items() if better}
#: what each column means
METRIC_HELP = {name: text for name, (_, text) in METRICS.items()}

#: per-image row entries that are not averaged into the table: identifiers, and ``rot-err`` (the image's rotation
#: error in degrees after the group's canonical-frame alignment), which the set metrics ``rot-*`` summarise
ROW_INFO = ("index", "group", "candidate", "rot-err")
