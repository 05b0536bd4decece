"""The training registry (dlacli.train.methods): a new training as it lands is its entry (this
file's toy) plus one `register(Training(...))` line, and `dla train --method` knows it by name:
it runs it with the options given, refuses the options it does not take in one line naming the
trainings that do, and lists it among the known ones."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dlacli.train import methods


def toy_training(data: Path, output: Path, options) -> Path:
    """Records what it was given: the options `dla train` passes an entry."""
    output.mkdir(parents=True, exist_ok=True)
    keep = ("steps_full", "targets", "seed", "batch")
    record = {"data": str(data), **{k: options[k] for k in keep}}
    (output / "toy.json").write_text(json.dumps(record))
    return output / "toy.json"


@pytest.fixture
def toy():
    methods.register(methods.Training("toy", "a test's toy", toy_training, frozenset({"targets"})))
    yield
    methods.TRAININGS.pop("toy")


def test_a_new_training_is_run_by_its_name(toy, tmp_path, dla):
    data = tmp_path / "data"
    data.mkdir()
    base = ["train", "--method", "toy", "--data", data, "-o", tmp_path / "run"]
    code, out, err = dla(*base, "--steps-full", "5", "--targets", "3")
    assert code == 0, err
    assert out.strip() == str(tmp_path / "run" / "toy.json")
    record = json.loads((tmp_path / "run" / "toy.json").read_text())
    assert record == {"data": str(data), "steps_full": 5, "targets": 3, "seed": 0, "batch": None}


@pytest.mark.parametrize(
    "extra, needle",
    [
        (["--gain"], "error: --gain: applies to --method residual only"),
        (["--jobs", "2"], "error: --jobs: applies to --method completion only"),
        (["--preset", "tiny"], "error: --preset: applies to --method learned or residual only"),
    ],
)
def test_options_a_training_does_not_take_are_refused(toy, tmp_path, dla, extra, needle):
    data = tmp_path / "data"
    data.mkdir()
    code, _, err = dla("train", "--method", "toy", "--data", data, "-o", tmp_path / "run", *extra)
    assert code == 2 and err.strip() == needle and not (tmp_path / "run").exists()


def test_an_unknown_training_lists_the_known_ones(toy, tmp_path, dla):
    code, _, err = dla("train", "--method", "nosuch", "--data", tmp_path, "-o", tmp_path / "run")
    assert code == 2 and "unknown method 'nosuch' (one of: learned, residual, completion, lifter, toy)" in err
    assert err.count("\n") == 1


def test_every_option_is_shared_or_taken_by_a_training():
    """An option no training reads would be refused for every method: none is."""
    import typer

    from dlacli.cli.app import app

    command = typer.main.get_command(app).commands["train"]
    options = {p.name for p in command.params if p.opts}
    takes = set().union(*(t.takes for t in methods.TRAININGS.values()))
    assert "gain" in options and options - methods.SHARED - takes == set()
    assert takes <= options and methods.SHARED <= options
