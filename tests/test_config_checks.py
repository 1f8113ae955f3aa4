"""Config files a hostile user writes: infinite and NaN numbers, keys given twice, files that
cannot be read. Each is refused when the file is read, in one line naming the key, the file and
what to do, and the CLI stops before it touches anything."""

from __future__ import annotations

import hashlib
import pathlib
import types
import typing
from pathlib import Path

import pytest
from pydantic import BaseModel

from fpp_graph.cli import main
from fpp_graph.config import Config, config_from_dict, load_config, plugin_sections
from fpp_graph.errors import ConfigError, InputDataError
from fpp_graph.yaml_files import read_yaml_file

GRAPH = """VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1
VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1
EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 100 0 0 0 0 0 100 0 0 0 0 100 0 0 0 25 0 0 25 0 25
"""


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _write(tmp_path: Path, text: str, name: str = "cfg.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _one_line_refusal(code: int, captured, *needles: str) -> str:
    assert code == 2, captured
    assert "Traceback" not in captured.err + captured.out
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("fpp-slam: error: "), captured.err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


# -- non-finite numbers ---------------------------------------------------------------------------
@pytest.mark.parametrize("literal", [".inf", "-.inf", ".nan", ".NaN", "+.Inf"])
@pytest.mark.parametrize(
    ("yaml_key", "dotted"),
    [
        ("fusion:\n  voxel_size_m: {}\n", "fusion.voxel_size_m"),
        ("fusion:\n  max_depth_m: {}\n", "fusion.max_depth_m"),
        ("pose_graph:\n  loop_false_alarm: {}\n", "pose_graph.loop_false_alarm"),
        ("evaluation:\n  reference_time_offset_s: {}\n", "evaluation.reference_time_offset_s"),
        ("registration:\n  ransac:\n    inlier_sigmas: {}\n", "registration.ransac.inlier_sigmas"),
        ("registration:\n  noise:\n    point_sigma_m: {}\n", "registration.noise.point_sigma_m"),
        ("decode:\n  min_modulation: {}\n", "decode.min_modulation"),
        ("registration:\n  ransac_threshold_m: {}\n", "registration.ransac_threshold_m"),  # an old flat key
    ],
)
def test_non_finite_number_is_refused_naming_its_key_and_file(tmp_path, yaml_key, dotted, literal):
    path = _write(tmp_path, yaml_key.format(literal))
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert "\n" not in message
    assert str(path) in message and f"{dotted} = " in message
    assert "not a finite number; give a finite value" in message


def test_every_non_finite_key_is_named_at_once(tmp_path):
    path = _write(tmp_path, "fusion:\n  voxel_size_m: .inf\n  tsdf_voxel_m: .nan\nrun:\n  workers: 2\n")
    message = str(pytest.raises(ConfigError, load_config, path).value)
    assert "fusion.voxel_size_m = .inf; fusion.tsdf_voxel_m = .nan: not a finite number" in message


def test_non_finite_under_an_unknown_key_or_in_a_list_is_named(tmp_path):
    path = _write(tmp_path, "fusoin:\n  sizes: [0.1, .inf]\n")
    message = str(pytest.raises(ConfigError, load_config, path).value)
    assert "fusoin.sizes[1] = .inf" in message


def _float_fields(model: type[BaseModel], prefix: str) -> typing.Iterator[str]:
    for name, field in model.model_fields.items():
        annotation = field.annotation
        args = typing.get_args(annotation) if isinstance(annotation, types.UnionType) else (annotation,)
        if float in args:
            yield f"{prefix}{name}"
        for arg in args:
            if isinstance(arg, type) and issubclass(arg, BaseModel):
                yield from _float_fields(arg, f"{prefix}{name}.")


def _nested(dotted: str, value: object) -> dict:
    out: dict = {}
    node = out
    *parents, last = dotted.split(".")
    for part in parents:
        node = node.setdefault(part, {})
    node[last] = value
    return out


def _every_float_key() -> list[str]:
    keys = list(_float_fields(Config, ""))
    for section, model in plugin_sections().items():
        keys.extend(_float_fields(model, f"{section}."))
    return keys


def test_every_float_key_of_every_section_refuses_infinity_and_nan_from_python_too():
    """The check is the models' own (``allow_inf_nan=False`` on their base), so a dict handed to
    config_from_dict, a string 'inf' and a new key are covered too, not just the keys listed here."""
    keys = _every_float_key()
    assert len(keys) > 10 and "fusion.voxel_size_m" in keys
    for dotted in keys:
        for value in (float("inf"), float("-inf"), float("nan"), "inf"):
            with pytest.raises(ConfigError, match=rf"{dotted}: Input should be a finite number"):
                config_from_dict(_nested(dotted, value))


def test_large_finite_numbers_and_nulls_still_pass(tmp_path):
    path = _write(tmp_path, "fusion:\n  voxel_size_m: 1.0e+300\n  max_depth_m: null\nevaluation:\n  reference_time_offset_s: -0.02\n")
    config = load_config(path)
    assert config.fusion.voxel_size_m == 1e300 and config.fusion.max_depth_m is None


def test_cli_run_refuses_infinity_before_writing_anything(tmp_path, capsys):
    graph = _write(tmp_path, GRAPH, "g.g2o")
    path = _write(tmp_path, "fusion:\n  voxel_size_m: .inf\n")
    before = {p: _sha256(p) for p in (graph, path)}
    out = tmp_path / "results"
    code = main(["run", str(graph), "--config", str(path), "--out", str(out)])
    _one_line_refusal(code, capsys.readouterr(), str(path), "fusion.voxel_size_m = .inf", "give a finite value")
    assert not out.exists()
    assert {p: _sha256(p) for p in before} == before


def test_cli_config_dump_refuses_nan(tmp_path, capsys):
    path = _write(tmp_path, "registration:\n  icp:\n    information_scale: .nan\n")
    code = main(["config", "dump", "--config", str(path)])
    _one_line_refusal(code, capsys.readouterr(), str(path), "registration.icp.information_scale = .nan")


# -- keys given twice -----------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("text", "key", "lines"),
    [
        ("fusion:\n  voxel_size_m: 0.002\n  mesh: false\n  voxel_size_m: 0.004\n", "fusion.voxel_size_m", (2, 4)),
        ("fusion:\n  mesh: false\nrun:\n  workers: 2\nfusion:\n  voxel_size_m: 0.004\n", "fusion", (1, 5)),
        ("registration:\n  gates: {min_inliers: 20, min_inliers: 30}\n", "registration.gates.min_inliers", (2, 2)),
        ("registration:\n  ransac:\n    inlier_sigmas: 4\n\n    'inlier_sigmas': 5\n", "registration.ransac.inlier_sigmas", (3, 5)),
    ],
)
def test_duplicated_key_is_refused_naming_key_file_and_both_lines(tmp_path, text, key, lines):
    path = _write(tmp_path, text)
    message = str(pytest.raises(ConfigError, load_config, path).value)
    assert message.startswith(f"{path}:{lines[1]}: {key} is given twice (lines {lines[0]} and {lines[1]})"), message
    assert "remove one of them" in message


def test_merged_keys_may_be_overridden(tmp_path):
    path = _write(tmp_path, "x-common: &common\n  mesh: false\n  voxel_size_m: 0.003\n")
    text = path.read_text() + "fusion:\n  <<: *common\n  voxel_size_m: 0.004\n"
    data = read_yaml_file(_write(tmp_path, text, "merged.yaml"))
    assert data["fusion"] == {"mesh": False, "voxel_size_m": 0.004}


def test_keys_equal_as_values_are_one_key(tmp_path):
    path = _write(tmp_path, "1: a\n0x1: b\n", "ints.yaml")
    with pytest.raises(ConfigError, match=r"ints\.yaml:2: 0x1 is given twice \(lines 1 and 2\)"):
        read_yaml_file(path)


def test_cli_refuses_a_duplicated_key_in_one_line(tmp_path, capsys):
    graph = _write(tmp_path, GRAPH, "g.g2o")
    path = _write(tmp_path, "pose_graph:\n  robust: none\n  robust: gnc\n")
    before = _sha256(path)
    out = tmp_path / "results"
    code = main(["run", str(graph), "--config", str(path), "--out", str(out)])
    _one_line_refusal(code, capsys.readouterr(), f"{path}:3", "pose_graph.robust is given twice (lines 2 and 3)")
    assert not out.exists() and _sha256(path) == before


def test_other_yaml_files_read_by_the_project_refuse_duplicates_too(tmp_path):
    """Every user YAML goes through read_yaml_file (calibrations, pattern files, sequence.yaml,
    scene definitions); its caller chooses the error type."""
    path = _write(tmp_path, "kind: gray_code\ngray_bits: 3\nkind: phase_shift\n", "patterns.yaml")
    with pytest.raises(InputDataError, match=r"patterns\.yaml:3: kind is given twice \(lines 1 and 3\)"):
        read_yaml_file(path, InputDataError, "pattern file")


# -- files that cannot be read --------------------------------------------------------------------
def test_config_that_is_a_folder_or_missing(tmp_path, capsys):
    folder = tmp_path / "cfg.yaml"
    folder.mkdir()
    with pytest.raises(ConfigError, match=rf"cannot read config {folder}: it is a folder; give the path of the file itself"):
        load_config(folder)
    code = main(["config", "dump", "--config", str(tmp_path / "absent.yaml")])
    _one_line_refusal(code, capsys.readouterr(), "absent.yaml", "no such file; check the path")


def test_unreadable_config_says_permission_denied_and_what_to_do(tmp_path, monkeypatch, capsys):
    path = _write(tmp_path, "run:\n  workers: 1\n")
    real = pathlib.Path.read_text

    def denied(self, *args, **kwargs):  # chmod 000 does not stop root, which the tests may run as
        if self == path:
            raise PermissionError(13, "Permission denied", str(self))
        return real(self, *args, **kwargs)

    monkeypatch.setattr(pathlib.Path, "read_text", denied)
    code = main(["config", "dump", "--config", str(path)])
    _one_line_refusal(code, capsys.readouterr(), str(path), "Permission denied", "check the file's permissions")


def test_non_utf8_file_message_names_its_role_once(tmp_path):
    path = tmp_path / "patterns.yaml"
    path.write_bytes(b"kind: \xff\xfe\n")
    message = str(pytest.raises(ConfigError, read_yaml_file, path, ConfigError, "pattern file").value)
    assert "file file" not in message
    assert message == f"{path}: not UTF-8 text, so not a YAML pattern file; give the pattern file as a YAML text file"
