"""css_node's publishers: per-frame images and view point, candidate scores (SPEC §8)."""
from __future__ import annotations

from typing import Any

import numpy as np
from rclpy.duration import Duration
from rclpy.node import Node
from sensor_msgs.msg import Image, PointCloud2

from ..engine.classes import ClassSet
from ..io.outputs import frame_output_images
from ..io.topics import FRAME_OUTPUTS, OUTPUT_TOPICS, POINTCLOUD2_TYPE
from . import conversions as rc
from .params import NodeParams
from .work import FrameJob


class OutputPublisher:
    """Creates the enabled ``~/<output>`` publishers and publishes the worker's results.

    Every per-frame output carries the frame's input stamp; images the input frame_id, the view point the
    map frame. ``~/candidate_scores`` is always published (it answers requests).
    """

    def __init__(self, node: Node, params: NodeParams, classes: ClassSet, depth: int = 10) -> None:
        self.p = params
        self.classes = classes
        self.pubs: dict[str, Any] = {}
        for name, msgtype in OUTPUT_TOPICS.items():
            if name in FRAME_OUTPUTS and not getattr(params, f"publish_{name}"):
                continue
            typ = PointCloud2 if msgtype == POINTCLOUD2_TYPE else Image
            self.pubs[name] = node.create_publisher(typ, f"~/{name}", depth)

    def publish_frame(self, job: FrameJob, view: Any) -> None:
        header = rc.header_msg(job.stamp_ns, job.frame_id)
        wanted = [n for n in ("semantic", "semantic_color", "expectation", "variance", "rendered_image")
                  if n in self.pubs]
        if wanted:
            images = frame_output_images(view, self.classes, self.p.ignore_label)
            for name in wanted:
                array, encoding = images[name]
                self.pubs[name].publish(rc.image_msg(array, encoding, header))
        if "view_uncertainty" in self.pubs:
            cloud = rc.view_points_msg(rc.header_msg(job.stamp_ns, self.p.map_frame), job.position[None],
                                       job.quat_in[None], np.array([view.u_var]), np.array([view.u_exp]))
            self.pubs["view_uncertainty"].publish(cloud)

    def publish_scores(self, header: Any, positions: np.ndarray, quats: np.ndarray, u_var: np.ndarray,
                       u_exp: np.ndarray) -> None:
        """One point per candidate in request order; the header echoes the request header."""
        self.pubs["candidate_scores"].publish(
            rc.view_points_msg(rc.copy_header(header), positions, quats, u_var, u_exp))

    def flush(self, timeout_s: float = 1.0) -> bool:
        """Wait up to ``timeout_s`` [s] until reliable subscribers acknowledged every candidate answer."""
        try:
            return bool(self.pubs["candidate_scores"].wait_for_all_acked(Duration(nanoseconds=int(timeout_s * 1e9))))
        except Exception:  # noqa: BLE001 - best effort at shutdown (middleware without the feature)
            return False
