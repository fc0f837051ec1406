"""The topic table of SPEC §8, written once: input topics (relative, remappable), the node's outputs.

Keys are the *kinds* used everywhere in the code (node, replay, demo generator, player, importers);
values are the default names. A bag written by the demo generator or an importer uses the absolute
input names (``/image`` ...); the node subscribes to the relative ones and publishes its outputs
under its private namespace (``~/semantic`` = ``/css_node/semantic``).
"""
from __future__ import annotations

IMAGE_TYPE = "sensor_msgs/msg/Image"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED_TYPE = "geometry_msgs/msg/PoseStamped"
POSE_ARRAY_TYPE = "geometry_msgs/msg/PoseArray"
POINTCLOUD2_TYPE = "sensor_msgs/msg/PointCloud2"
#: pose_type (node parameter, css_replay option) -> message type of the pose stream.
POSE_TYPES: dict[str, str] = {
    "pose_stamped": POSE_STAMPED_TYPE,
    "pose_with_covariance": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "odometry": "nav_msgs/msg/Odometry",
}

#: Where a camera pose comes from (node parameter ``pose_source``, css_replay ``--pose-source``): a pose topic
#: (``pose_type``, composed with ``camera_extrinsics``), or the TF lookup ``map_frame <- header.frame_id`` of each
#: segmentation at its stamp from ``/tf`` and ``/tf_static``.
POSE_SOURCES = ("topic", "tf")
TF_TYPE = "tf2_msgs/msg/TFMessage"
#: Absolute TF topics (never namespaced, as every robot stack publishes them).
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"

NODE_NAME = "css_node"

#: kind -> relative topic name the node subscribes to (remap with ``--ros-args -r``).
INPUT_TOPICS: dict[str, str] = {
    "image": "image",
    "segmentation": "segmentation",
    "confidence": "segmentation_confidence",
    "camera_info": "camera_info",
    "pose": "pose",
    "candidates": "candidates",
    "point_queries": "point_queries",
}
#: kind -> message type of each input.
INPUT_TYPES: dict[str, str] = {
    "image": IMAGE_TYPE,
    "segmentation": IMAGE_TYPE,
    "confidence": IMAGE_TYPE,
    "camera_info": CAMERA_INFO_TYPE,
    "pose": POSE_STAMPED_TYPE,
    "candidates": POSE_ARRAY_TYPE,
    "point_queries": POINTCLOUD2_TYPE,
    "gt": IMAGE_TYPE,
    "depth": IMAGE_TYPE,
    "gt_changed": IMAGE_TYPE,
}
#: The frame kinds a bag holds (absolute names): the node's inputs, the measured depth (sensor_msgs/Image, REP 118:
#: 16UC1 millimetres or 32FC1 metres, registered to the segmentation) and the evaluation-only labels: the static
#: ground truth and, for a world that changes, the class at the end of the bag of the pixels whose class changes
#: (ignore label elsewhere).
BAG_TOPICS: dict[str, str] = {
    "image": "/image",
    "segmentation": "/segmentation",
    "confidence": "/segmentation_confidence",
    "camera_info": "/camera_info",
    "pose": "/pose",
    "gt": "/segmentation_gt",
    "depth": "/depth",
    "gt_changed": "/segmentation_gt_changed",
}
#: Kinds every usable bag must have; the others are optional.
REQUIRED_BAG_KINDS = ("segmentation", "pose", "camera_info")
#: Header frame ids and first stamp of the bags this package writes (demo generator, importers): images and
#: camera_info in the camera's optical frame, poses in the map frame; frame 0 at a fixed stamp [ns] (no wall
#: clock in the output, so equal input gives byte-identical bags).
BAG_CAMERA_FRAME = "camera_optical"
BAG_MAP_FRAME = "map"
BAG_START_NS = 1_700_000_000_000_000_000

#: name -> message type of the node's private outputs (``~/<name>``), in publishing order.
OUTPUT_TOPICS: dict[str, str] = {
    "semantic": IMAGE_TYPE,
    "semantic_color": IMAGE_TYPE,
    "expectation": IMAGE_TYPE,
    "variance": IMAGE_TYPE,
    "rendered_image": IMAGE_TYPE,
    "confidence": IMAGE_TYPE,
    "surprise": IMAGE_TYPE,
    "view_uncertainty": POINTCLOUD2_TYPE,
    "candidate_scores": POINTCLOUD2_TYPE,
    "semantic_cloud": POINTCLOUD2_TYPE,
    "point_query_results": POINTCLOUD2_TYPE,
}
#: Outputs published for every observed frame (``candidate_scores`` and ``point_query_results`` answer
#: requests; ``semantic_cloud`` is the 3D map, published periodically with transient-local durability).
#: ``confidence`` only exists when the node's sensor model holds a calibrated confidence map; ``surprise`` only with
#: output_scale 1 (the update at full resolution makes it).
FRAME_OUTPUTS = ("semantic", "semantic_color", "expectation", "variance", "rendered_image", "confidence",
                 "surprise", "view_uncertainty")


def output_topic(name: str, node_name: str = NODE_NAME) -> str:
    """Absolute name of a node output, e.g. ``/css_node/semantic``."""
    return f"/{node_name.strip('/')}/{name}"


def camera_bag_topics(cameras: list[str] | tuple[str, ...], topics: dict[str, str],
                      pose_per_camera: bool = False) -> list[dict[str, str]]:
    """Absolute bag topics per camera: kind -> topic (the node's names under each namespace).

    ``topics`` holds the one-camera names (css_replay's ``--<kind>-topic`` options; '' disables a kind); with
    the single un-namespaced camera they are used as they are. Camera ``ns`` reads ``/<ns>/<relative name>``
    (GT ``/<ns>/segmentation_gt``); the pose topic is shared unless ``pose_per_camera``.
    """
    cams = [c.strip("/") for c in cameras]
    if cams == [""]:
        return [dict(topics)]
    out = []
    for ns in cams:
        per: dict[str, str] = {}
        for kind, default in BAG_TOPICS.items():
            if not topics.get(kind):
                per[kind] = ""
            elif kind == "pose" and not pose_per_camera:
                per[kind] = topics["pose"]
            else:
                per[kind] = f"/{ns}{default}" if ns else topics[kind]
        out.append(per)
    return out
