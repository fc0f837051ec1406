"""css_node's class setup: another model given num_classes never gets the demo's class file."""
from __future__ import annotations

import pytest

import ros_helpers as rh
from css_ros.engine.classes import ClassSet
from css_ros.errors import ConfigError
from css_ros.ros.params import DEFAULT_CLASSES, NodeParams
from css_ros.ros.startup import load_classes, load_engine


def test_num_classes_with_the_default_class_file_gives_anonymous_classes(tmp_path):
    model = rh.write_wall_model(tmp_path / "my.ply")
    warnings: list[str] = []
    p = NodeParams(model_path=str(model), num_classes=12, checkpoint_path="")
    assert p.class_file == DEFAULT_CLASSES  # left at the demo's default
    engine = load_engine(p, lambda s: None, warnings.append)
    assert engine.smap.num_classes == 12
    assert engine.classes.names == ClassSet.default(12).names != ClassSet.from_yaml(rh.REPO / DEFAULT_CLASSES).names[:12]
    assert any("anonymous" in w and "num_classes=12" in w for w in warnings)


def test_num_classes_contradicting_a_set_class_file_is_a_start_up_error(tmp_path):
    ClassSet.default(5).to_yaml(tmp_path / "five.yaml")
    p = NodeParams(class_file=str(tmp_path / "five.yaml"), num_classes=12)
    with pytest.raises(ConfigError, match=r"num_classes=12 contradicts class_file=.*five.yaml.*5 classes"):
        load_classes(p, print)
    assert load_classes(NodeParams(class_file=str(tmp_path / "five.yaml"), num_classes=5), print).num_classes == 5
    assert load_classes(NodeParams(class_file=str(tmp_path / "five.yaml")), print).num_classes == 5
    assert load_classes(NodeParams(), print).num_classes == ClassSet.from_yaml(rh.REPO / DEFAULT_CLASSES).num_classes
