"""``unicorn-data``'s command line: usage errors name the subcommand and the options the user typed."""

from __future__ import annotations

from pathlib import Path

import pytest

from unicorn.cli.data import main
from unicorn.data.images import DatasetError
from unicorn.data.synthetic import writer
from unicorn.data.synthetic.sampling import check_view_ranges

SMALL = ["--models", "3", "--views", "1", "--size", "8", "--supersample", "1", "--points", "100", "--quiet"]
MUGS = ["--category", "mug", *SMALL]


def _usage_error(argv: list[str], capsys: pytest.CaptureFixture[str]) -> list[str]:
    """The lines on stderr of a usage error of argparse (status 2)."""
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    return capsys.readouterr().err.splitlines()


@pytest.mark.parametrize(
    ("argv", "error"),
    [
        (["synth", "--bogus"], "unrecognized arguments: --bogus"),
        (["check", "synthetic", "--root", "DIR", "--bogus", "1"], "unrecognized arguments: --bogus 1"),
        (["check", "synthetic", "extra", "--root", "DIR"], "unrecognized arguments: extra"),
        (["check", "synthetic", "--root", "DIR", "--max-image-pixels", "-1"], "--max-image-pixels must be >= 0"),
        (["check", "synthetic"], "the following arguments are required: --root"),
        (["check", "synthetic", "--root", "DIR", "--split", "dev"], "argument --split: invalid choice: 'dev'"),
    ],
    ids=["synth-unknown", "check-unknown", "check-extra", "check-limit", "check-no-root", "check-split"],
)
def test_a_usage_error_shows_the_subcommands_usage_and_one_line(
    argv: list[str], error: str, capsys: pytest.CaptureFixture[str]
) -> None:
    lines = _usage_error(argv, capsys)
    command = f"unicorn-data {argv[0]}"
    assert lines[0].startswith(f"usage: {command} [-h]"), lines
    assert lines[-1].startswith(f"{command}: error: {error}"), lines
    assert sum("error" in line for line in lines) == 1


@pytest.mark.parametrize(("command", "words"), [("check", "item count"), ("synth", "ShapeNet-NMR (DVR) layout")])
def test_a_subcommands_help_says_what_it_does(command: str, words: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main([command, "--help"])
    assert info.value.code == 0
    help_text = " ".join(capsys.readouterr().out.split())
    assert help_text.startswith(f"usage: unicorn-data {command}")
    description = help_text[help_text.index("] ") : help_text.index("options:")]
    assert words in description


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--models", "2"], "--models must be at least 3 (one model per split: train, val, test), got 2"),
        (["--mode", "nmr", "--roll", "5"], "--roll=5.0 is for the wild mode; the nmr mode's views have none"),
        (["--mode", "wild", "--shift", "2"], "--shift must be a number in [0, 1], got 2.0"),
        (
            ["--mode", "wild", "--background-kinds", "solid,foo"],
            "--background-kinds must be some of ['solid', 'gradient', 'checker', 'noise'], got ['solid', 'foo']",
        ),
        (
            ["--background-kinds", "solid"],
            "--background-kinds solid picks random backgrounds, but --mode nmr draws white backgrounds: add "
            "--backgrounds random, or drop --background-kinds",
        ),
        (
            ["--mode", "wild", "--backgrounds", "white", "--background-kinds", "noise"],
            "--background-kinds noise picks random backgrounds, but --backgrounds white: add --backgrounds random, "
            "or drop --background-kinds",
        ),
    ],
    ids=["models", "roll-in-nmr", "shift", "unknown-kind", "kinds-in-nmr", "kinds-on-white"],
)
def test_synth_names_the_option_given(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    for where in (["--out", str(tmp_path / "data")], []):  # a folder of the user's, and the cache
        assert main(["synth", *MUGS, *where, *args]) == 2
        assert capsys.readouterr().err == f"unicorn-data: error: {message}\n"
    assert list(tmp_path.iterdir()) == []


def test_the_generators_own_checks_name_its_arguments(tmp_path: Path) -> None:
    """Called from Python, the checks that ``unicorn-data synth`` words with its options name the arguments."""
    with pytest.raises(DatasetError, match=r"^n_models must be at least 3 \(one model per split"):
        writer.check_generation_counts(2, 1)
    with pytest.raises(DatasetError, match=r"^roll=5 is for the wild mode"):
        check_view_ranges("nmr", roll=5)
    with pytest.raises(DatasetError, match=r"^background_kinds \['solid'\] asks for random backgrounds"):
        writer.generate_synthetic_dataset(tmp_path / "data", "mug", "nmr", 3, background_kinds=["solid"])
    assert list(tmp_path.iterdir()) == []


def test_synth_names_the_options_a_generated_dataset_differs_in(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A folder generated with other settings is refused naming the options, into --out and into the cache."""
    monkeypatch.setenv("UNICORN_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "data"
    assert main(["synth", *MUGS, "--out", str(out)]) == 0
    assert main(["synth", *MUGS]) == 0
    capsys.readouterr()
    cars = ["--category", "car", *SMALL, "--out", str(out)]
    cases = [
        (["--size", "16"], "--size 8 (asked: 16)"),
        (["--views", "2"], "--views 1 (asked: 2)"),
        (["--points", "200"], "--points 100 (asked: 200)"),
        (["--backgrounds", "random"], "--backgrounds unset (asked: random)"),
    ]
    for args, difference in cases:
        assert main(["synth", *cars, *args]) == 2
        assert capsys.readouterr().err == (
            f"unicorn-data: error: {out} holds a synthetic dataset generated with {difference}; other categories "
            "join it only with the same settings: generate into another folder\n"
        )
    cached = writer.synthetic_dataset_path("mug", "nmr", 3, 0)
    kinds = "--backgrounds unset (asked: random), --background-kinds unset (asked: solid,noise)"
    for args, difference in [*cases, (["--backgrounds", "random", "--background-kinds", "solid,noise"], kinds)]:
        assert main(["synth", *MUGS, *args]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"unicorn-data: error: the synthetic dataset in {cached} was generated with {difference}")
        assert err.count("\n") == 1


def test_synth_says_how_to_generate_elsewhere_than_a_cache_folder_it_cannot_use(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A cache folder of other settings, with a damaged synthetic.json or holding other files is refused naming
    --out, the option that generates elsewhere (the folder's name holds neither --size nor the other options)."""
    monkeypatch.setenv("UNICORN_CACHE", str(tmp_path / "cache"))
    assert main(["synth", *MUGS]) == 0
    capsys.readouterr()
    remedy = "or generate into another folder with --out DIR\n"
    assert main(["synth", *MUGS, "--size", "16"]) == 2
    err = capsys.readouterr().err
    assert err.endswith(f"was generated with --size 8 (asked: 16); delete that folder to generate it again, {remedy}")
    cached = writer.synthetic_dataset_path("mug", "nmr", 3, 0)
    (cached / "synthetic.json").write_text("[1, 2]")
    assert main(["synth", *MUGS]) == 2
    assert capsys.readouterr().err.endswith(f"delete {cached} to generate it again, {remedy}")
    other = writer.synthetic_dataset_path("mug", "nmr", 3, 1)
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    assert main(["synth", *MUGS, "--seed", "1"]) == 2
    assert capsys.readouterr().err == (
        f"unicorn-data: error: {other} holds files but no synthetic.json: it is not a generated dataset; move it "
        f"away, {remedy}"
    )


def test_synth_into_a_folder_under_a_file_names_the_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "notes").write_text("mine")
    out = tmp_path / "notes" / "data" / "mugs"
    assert main(["synth", *MUGS, "--out", str(out)]) == 2
    assert capsys.readouterr().err == (
        f"unicorn-data: error: cannot write {out}: {tmp_path / 'notes'} is a file, where a folder goes\n"
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes"] and (tmp_path / "notes").read_text() == "mine"


@pytest.mark.parametrize(
    ("argv", "error"),
    [
        (
            ["--categories", "chair", "synthetic", "--root", "DIR"],
            "the following arguments are required: dataset (--categories took every word after it: name the dataset "
            "before --categories)",
        ),
        (
            ["--cat", "chair", "car", "synthetic"],
            "the following arguments are required: dataset, --root (--categories took every word after it: name "
            "the dataset before --categories)",
        ),
        (["--categories", "--root", "DIR"], "the following arguments are required: dataset"),
        (["--root", "DIR"], "the following arguments are required: dataset"),
    ],
    ids=["categories-took-it", "prefix-took-it", "categories-empty", "no-categories"],
)
def test_check_says_when_categories_took_the_datasets_name(
    argv: list[str], error: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _usage_error(["check", *argv], capsys)[-1] == f"unicorn-data check: error: {error}"
    assert main(["check", "synthetic", "--root", "DIR", "--categories", "chair", "car"]) == 2  # after it: read
    assert "synthetic dataset not found at" in capsys.readouterr().err
