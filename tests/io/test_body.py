"""body.json: golden file, round trips and every bad-input case (formats/body.md)."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from dlacli.errors import DlaInputError
from dlacli.io.body import body_from_dict, body_to_dict, read_body, summarize_body, write_body
from dlacli.types import PHENOTYPE_KEYS, BodyParams

VALID = {
    "format": "dla.body/1",
    "model": "anny",
    "phenotype": {"gender": 0.0, "age": 0.5, "muscle": 1.0, "weight": 0.25, "height": 0.75, "proportions": 0.5},
    "root_rotation": [0.1, -0.2, 0.3],
    "root_translation": [0.0, 0.5, -1.0],
    "pose": {"upperarm01.L": [0.0, 0.5, 0.0], "head": [0.1, 0.0, -0.1]},
}


def _write(tmp_path, obj, name="body.json"):
    path = tmp_path / name
    path.write_text(obj if isinstance(obj, str) else json.dumps(obj))
    return path


def _error(path) -> str:
    with pytest.raises(DlaInputError) as info:
        read_body(path)
    msg = str(info.value)
    assert "\n" not in msg
    assert str(path) in msg
    return msg


def test_golden_file_matches_an_independent_json_parse(formats_dir):
    path = formats_dir / "examples" / "body.json"
    raw = json.loads(path.read_text())
    body = read_body(path)
    assert raw["format"] == "dla.body/1" and body.model == raw["model"] == "anny"
    assert body.phenotype == raw["phenotype"]
    np.testing.assert_array_equal(body.root_rotation, raw["root_rotation"])
    np.testing.assert_array_equal(body.root_translation, raw["root_translation"])
    assert list(body.pose) == list(raw["pose"])
    for label, value in raw["pose"].items():
        np.testing.assert_array_equal(body.pose[label], value)


def test_round_trip(tmp_path):
    body = body_from_dict(VALID, "test")
    write_body(body, tmp_path / "b.json")
    assert json.loads((tmp_path / "b.json").read_text()) == VALID
    back = read_body(tmp_path / "b.json")
    assert back.phenotype == body.phenotype and back.model == "anny"
    np.testing.assert_array_equal(back.root_rotation, body.root_rotation)
    np.testing.assert_array_equal(back.root_translation, body.root_translation)
    assert back.pose.keys() == body.pose.keys()
    for k in body.pose:
        np.testing.assert_array_equal(back.pose[k], body.pose[k])
    assert body_to_dict(back) == VALID


def test_numpy_values_are_written_as_plain_json(tmp_path):
    body = BodyParams(
        phenotype={k: np.float32(0.25) for k in PHENOTYPE_KEYS},
        root_rotation=np.array([0.0, 0.0, 1.5], np.float32),
        pose={"head": np.array([0.5, 0.0, 0.0], np.float32)},
    )
    write_body(body, tmp_path / "b.json")
    raw = json.loads((tmp_path / "b.json").read_text())
    assert raw["phenotype"]["age"] == 0.25 and raw["root_rotation"] == [0.0, 0.0, 1.5]
    assert raw["pose"] == {"head": [0.5, 0.0, 0.0]}


def test_optional_keys_default_to_rest(tmp_path):
    d = {k: VALID[k] for k in ("format", "model", "phenotype")}
    body = read_body(_write(tmp_path, d))
    np.testing.assert_array_equal(body.root_rotation, np.zeros(3))
    np.testing.assert_array_equal(body.root_translation, np.zeros(3))
    assert body.pose == {}
    assert read_body(_write(tmp_path, {**d, "pose": {}})).pose == {}


def test_bounds_are_inclusive(tmp_path):
    d = copy.deepcopy(VALID)
    d["phenotype"] = {k: float(i % 2) for i, k in enumerate(PHENOTYPE_KEYS)}
    assert read_body(_write(tmp_path, d)).phenotype["age"] == 1.0


def _mutated(path_value_pairs=(), delete=()):
    d = copy.deepcopy(VALID)
    for keys in delete:
        target = d
        for k in keys[:-1]:
            target = target[k]
        del target[keys[-1]]
    for keys, value in path_value_pairs:
        target = d
        for k in keys[:-1]:
            target = target[k]
        target[keys[-1]] = value
    return d


@pytest.mark.parametrize(
    "doc, needle",
    [
        (_mutated(delete=[("format",)]), "missing 'format'"),
        (_mutated([(("format",), "dla.body/2")]), "'dla.body/2' is not supported"),
        (_mutated([(("format",), "dla.motion/1")]), "expected 'dla.body/1'"),
        (_mutated(delete=[("phenotype",)]), "missing key 'phenotype'"),
        (_mutated(delete=[("model",)]), "missing key 'model'"),
        (_mutated([(("model",), "smplx")]), "model 'smplx' is not supported"),
        (_mutated(delete=[("phenotype", "age")]), "phenotype is missing 'age'"),
        (_mutated([(("phenotype", "bmi"), 0.5)]), "unknown phenotype key 'bmi'"),
        (_mutated([(("phenotype", "age"), 1.2)]), "phenotype.age = 1.2 is outside [0, 1]"),
        (_mutated([(("phenotype", "muscle"), -0.1)]), "phenotype.muscle = -0.1 is outside [0, 1]"),
        (_mutated([(("phenotype", "gender"), "female")]), "phenotype.gender must be a number"),
        (_mutated([(("phenotype", "gender"), True)]), "phenotype.gender must be a number"),
        (_mutated([(("phenotype",), [0.5] * 6)]), "phenotype must be an object"),
        (_mutated([(("root_rotation",), [0.0, 1.0])]), "root_rotation has shape (2,), expected (3,)"),
        (_mutated([(("root_translation",), "up")]), "root_translation must hold numbers"),
        (_mutated([(("pose", "head"), [0.1, 0.2, 0.3, 0.4])]), "pose['head'] has shape (4,), expected (3,)"),
        (_mutated([(("pose", "head"), ["a", "b", "c"])]), "pose['head'] must hold numbers"),
        (_mutated([(("pose",), [[0, 0, 0]])]), "pose must be an object"),
        (_mutated([(("root_translaton",), [0, 0, 0])]), "unknown key 'root_translaton'"),
    ],
)
def test_bad_documents_are_one_line_errors(tmp_path, doc, needle):
    assert needle in _error(_write(tmp_path, doc))


@pytest.mark.parametrize(
    "text, needle",
    [
        (json.dumps(VALID).replace("0.75", "NaN"), "phenotype.height is not finite"),
        (json.dumps(VALID).replace("0.3]", "Infinity]"), "root_rotation has 1 non-finite value"),
        (json.dumps(VALID).replace('"head": [0.1', '"head": [NaN'), "pose['head'] has 1 non-finite value"),
        (json.dumps(VALID)[:57], "not valid JSON"),
        ("", "not valid JSON"),
        ("[1, 2, 3]", "expected a JSON object"),
    ],
)
def test_bad_text_is_a_one_line_error(tmp_path, text, needle):
    assert needle in _error(_write(tmp_path, text))


def test_missing_file(tmp_path):
    assert "no such file" in _error(tmp_path / "nope.json")


def test_writer_rejects_an_invalid_body_and_leaves_no_file(tmp_path):
    body = body_from_dict(VALID, "test")
    body.phenotype["age"] = 2.0
    with pytest.raises(DlaInputError, match="age"):
        write_body(body, tmp_path / "b.json")
    assert list(tmp_path.iterdir()) == []


def test_summary(formats_dir):
    s = summarize_body(formats_dir / "examples" / "body.json")
    raw = json.loads((formats_dir / "examples" / "body.json").read_text())
    assert s["kind"] == "body" and s["format"] == "dla.body/1"
    assert s["phenotype"] == raw["phenotype"] and s["posed_bones"] == len(raw["pose"])
    norms = {k: np.linalg.norm(v) for k, v in raw["pose"].items()}
    assert s["largest_rotation"]["bone"] == max(norms, key=norms.get)
    json.dumps(s)
