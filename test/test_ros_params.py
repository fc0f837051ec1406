"""css_node parameter table: config/css_node.yaml and docs/parameters.md match it; coercion and validation."""
from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import pytest
import yaml

from css_ros.engine import spec
from css_ros.errors import ConfigError
from css_ros.io.frames import DEFAULT_MAX_IMAGE_PIXELS
from css_ros.ros.params import (NodeParams, check_params, checkpoint_file, coerce, param_table, params_from_values,
                                params_markdown)

REPO = Path(__file__).resolve().parents[1]


def test_yaml_holds_exactly_the_table_in_order_with_its_defaults():
    yaml_params = yaml.safe_load((REPO / "config" / "css_node.yaml").read_text())["css_node"]["ros__parameters"]
    table = [(name, default) for name, default, _, _ in param_table()]
    assert list(yaml_params) == [name for name, _ in table]
    assert {name: yaml_params[name] for name, _ in table} == dict(table)


def test_docs_parameters_md_is_up_to_date():
    assert (REPO / "docs" / "parameters.md").read_text() == params_markdown(), \
        "regenerate: python -c 'from css_ros.ros.params import params_markdown; print(params_markdown(), end=\"\")'" \
        " > docs/parameters.md"


def test_every_parameter_has_a_description_and_seconds_for_times():
    for name, _, unit, desc in param_table():
        assert len(desc) > 10, name
        if name.endswith(("_period", "_slop", "_future", "_budget", "_retry_max")):
            assert unit == "s", name
    assert {f.name for f in fields(NodeParams) if f.name.startswith("publish_")} == {
        "publish_semantic", "publish_semantic_color", "publish_expectation", "publish_variance",
        "publish_rendered_image", "publish_confidence", "publish_surprise", "publish_view_uncertainty", "publish_diagnostics",
        "publish_evidence"}


def test_defaults_come_from_the_engine_and_frame_decoder():
    p = NodeParams()
    assert (p.prior, p.background, p.ignore_label, p.unknown_threshold) == (
        spec.DEFAULT_PRIOR, spec.DEFAULT_BACKGROUND, spec.DEFAULT_IGNORE_LABEL, spec.DEFAULT_UNKNOWN_THRESHOLD)
    assert p.max_image_pixels == DEFAULT_MAX_IMAGE_PIXELS


@pytest.mark.parametrize("name, value, default, expected", [
    ("prior", 1, 0.5, 1.0), ("queue_size", 3.0, 10, 3), ("warmup", False, True, False),
    ("splat_to_map", (2, 0, 0, 0, 0, 0, 0, 1), [1.0], [2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]),
    ("cameras", ("front", "left"), [""], ["front", "left"]), ("map_frame", "odom", "map", "odom")])
def test_coerce_accepts(name, value, default, expected):
    out = coerce(name, value, default)
    assert out == expected and type(out) is type(expected)


@pytest.mark.parametrize("name, value, default", [
    ("prior", "lots", 0.5), ("prior", True, 0.5), ("queue_size", 2.5, 10), ("queue_size", True, 10),
    ("warmup", 1, True), ("map_frame", 3, "map"), ("splat_to_map", "abcd", [0.0]),
    ("splat_to_map", [0, "x"], [0.0]), ("cameras", [1, 2], [""])])
def test_coerce_refuses_with_config_error_naming_the_parameter(name, value, default):
    with pytest.raises(ConfigError, match=f"parameter {name}="):
        coerce(name, value, default)


@pytest.mark.parametrize("field, value", [("input_qos", "fast"), ("backend", "opencl"), ("prior", 0.0),
                                          ("queue_size", 0), ("sync_slop", -1.0), ("output_scale", float("nan")),
                                          ("output_scale", 2.0), ("candidate_scale", 1.5), ("max_image_pixels", 0),
                                          ("candidate_slice", 0), ("candidate_time_budget", float("inf")),
                                          ("checkpoint_retry_max", -1.0), ("num_classes", -1),
                                          ("ignore_label", 70000), ("prior", 1e300), ("background", 1e16),
                                          ("max_image_pixels", 8192 * 8192 + 1),
                                          ("unknown_threshold", 1.5),
                                          ("camera_extrinsics", [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0]),
                                          ("splat_to_map", [-1.0, 0, 0, 0, 0, 0, 0, 1]),
                                          ("pose_type", "odom"), ("pose_buffer", 0.0),
                                          ("pose_source", "tf2"), ("tf_buffer_s", 0.0),
                                          ("tf_buffer_s", float("inf")),
                                          ("cameras", ["cam1", "cäm2"]),
                                          ("camera_extrinsics", [1e308, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]),
                                          ("splat_to_map", [1.0, 0, 2e7, 0, 0, 0, 0, 1]),
                                          ("splat_to_map", [1e300, 0, 0, 0, 0, 0, 0, 1]),
                                          ("model_swap_min_ratio", 1.5), ("model_swap_min_ratio", float("nan")),
                                          ("model_swap_warn_ratio", -0.1),
                                          ("model_swap_warn_ratio", 0.5)])   # below model_swap_min_ratio 0.7
def test_check_params_rejects(field, value):
    p = NodeParams()
    setattr(p, field, value)
    with pytest.raises(ConfigError, match=field):
        check_params(p)


def test_pose_source_tf_refuses_pose_per_camera_and_an_empty_map_frame():
    for field, value in (("pose_per_camera", True), ("map_frame", "/")):
        p = NodeParams(pose_source="tf")
        setattr(p, field, value)
        with pytest.raises(ConfigError, match=field):
            check_params(p)
    check_params(NodeParams(pose_source="tf", cameras=["front", "left"]))


def test_params_from_values_coerces_checks_and_refuses_unknown_names():
    p = params_from_values({"prior": 2, "queue_size": 4.0})
    assert p.prior == 2.0 and p.queue_size == 4 and p.backend == "numba"
    with pytest.raises(ConfigError, match="num_clases"):
        params_from_values({"num_clases": 4})
    with pytest.raises(ConfigError, match="warn_period"):
        params_from_values({"warn_period": -1})


def test_default_checkpoint_is_per_model():
    template = NodeParams().checkpoint_path
    a, b = checkpoint_file(template, "ab" * 32), checkpoint_file(template, "cd" * 32)
    assert a != b and a.endswith("/maps/" + "ab" * 8 + ".npz")
    assert checkpoint_file("/tmp/x.npz", "ab" * 32) == "/tmp/x.npz"
