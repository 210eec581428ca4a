"""Evaluation metrics of UNICORN: Chamfer-L1 (with GT-pose alignment or ICP), normal consistency, mask IoU,
keypoint-transfer PCK, pose errors and voxel IoU; and instance-level metrics (colour error against the
mean-colour predictor, win share against a baseline, shape retrieval among the evaluated objects, shape spread,
flip rate, code spread and active units).

Each metric is a plain function on tensors; see the submodules for the protocols they follow.
"""

from .alignment import align_with_gt_pose, normalize_to_unit_cube
from .chamfer import (
    CHAMFER_FACTOR,
    PointCloudScores,
    chamfer_l1,
    chamfer_l2,
    chamfer_matrix,
    normal_consistency,
    point_cloud_scores,
)
from .icp import (
    ICPResult,
    apply_similarity,
    gradient_icp,
    matrix_to_rotation_6d,
    rotation_6d_to_matrix,
    transform_normals,
)
from .instance import (
    active_units,
    code_spread,
    color_errors,
    flip_rate,
    mean_foreground_color,
    rotation_accuracy,
    win_share,
)
from .keypoints import keypoint_pairs, keypoint_transfer_pck, pck, project_vertices, transfer_keypoints
from .masks import mask_iou
from .mesh_evaluator import SHAPENET_METRICS, evaluate_meshes
from .moving import MovingQueries
from .nn import NearestNeighborIndex, gather_points, nearest_neighbors, spatial_order
from .pose import (
    align_canonical_frame,
    azimuth_error,
    geodesic_error,
    pose_errors,
    rotation_to_azim_elev_roll,
)
from .sampling import MAX_POINTS, check_point_count, face_areas_normals, sample_points_from_meshes
from .shapes import mesh_spread, normalize_shape, retrieval_scores, shape_retrieval, shape_spread
from .voxels import mesh_voxel_iou, voxel_centers, voxel_iou, voxelize_mesh

__all__ = [
    "CHAMFER_FACTOR",
    "SHAPENET_METRICS",
    "ICPResult",
    "MAX_POINTS",
    "MovingQueries",
    "NearestNeighborIndex",
    "PointCloudScores",
    "active_units",
    "align_canonical_frame",
    "align_with_gt_pose",
    "apply_similarity",
    "azimuth_error",
    "chamfer_l1",
    "chamfer_l2",
    "chamfer_matrix",
    "code_spread",
    "color_errors",
    "evaluate_meshes",
    "face_areas_normals",
    "flip_rate",
    "gather_points",
    "geodesic_error",
    "gradient_icp",
    "keypoint_pairs",
    "keypoint_transfer_pck",
    "mask_iou",
    "matrix_to_rotation_6d",
    "mean_foreground_color",
    "mesh_spread",
    "mesh_voxel_iou",
    "nearest_neighbors",
    "normal_consistency",
    "normalize_shape",
    "normalize_to_unit_cube",
    "pck",
    "point_cloud_scores",
    "pose_errors",
    "project_vertices",
    "rotation_6d_to_matrix",
    "retrieval_scores",
    "rotation_accuracy",
    "rotation_to_azim_elev_roll",
    "check_point_count",
    "sample_points_from_meshes",
    "shape_retrieval",
    "shape_spread",
    "spatial_order",
    "transfer_keypoints",
    "transform_normals",
    "voxel_centers",
    "voxel_iou",
    "voxelize_mesh",
    "win_share",
]
