"""The run's text files (``config.yaml``, ``provenance.json``, ``heldout.csv``, ``csv/metrics.csv``) are UTF-8
whatever the locale: written and read with an explicit encoding, which ``-X warn_default_encoding`` checks."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import yaml

#: writes and reads every text file of a run in a folder named with non-ASCII characters; an open without an
#: encoding (the locale's) is an error
SCRIPT = """
import sys
import warnings
from pathlib import Path
from types import SimpleNamespace

from tests.support.training import TINY, compose_config
from unicorn.config import validate
from unicorn.lit.heldout import append_csv_row
from unicorn.lit.loggers import CSVLogger
from unicorn.lit.run import _evaluated_before, write_run_folder

out = Path(sys.argv[1])
typed = validate(compose_config([*TINY, f"paths.output_dir='{out}'"]))
warnings.simplefilter("error", EncodingWarning)  # from here on: the run's own files
write_run_folder(typed, out, None, [])
write_run_folder(typed, out, None, [])  # a second start: provenance.json read back
target = SimpleNamespace(
    dataset="synthetic", root=None, split="test", categories=None, max_images=None, dataset_options={}
)
_evaluated_before(out / "provenance.json", {}, target)  # a JSON file read as the evaluation's metrics.json
for step in (4, 8, 4):  # the last one a resume: the file is read back
    append_csv_row(out / "heldout.csv", {"step": step, "iou": 0.5})
logger = CSVLogger(str(out), name="csv", version="")
logger.log_metrics({"train/loss": 1.0}, step=0)
logger.log_metrics({"heldout/iou": 0.5}, step=1)  # a new column: the file is written anew
resumed = CSVLogger(str(out), name="csv", version="")  # reads the header of the file there
resumed.log_metrics({"train/loss": 2.0}, step=2)
resumed.experiment.drop_from(1)
"""


def test_the_run_writes_and_reads_its_text_files_as_utf8(tmp_path: Path) -> None:
    out = tmp_path / "données-été"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run(
        # the libraries' own opens at import are left out: the script turns the warning into an error after them
        [sys.executable, "-X", "warn_default_encoding", "-W", "ignore::EncodingWarning", "-c", SCRIPT, str(out)],
        cwd=Path(__file__).parents[2],
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    config = yaml.safe_load((out / "config.yaml").read_bytes().decode("utf-8"))
    assert config["paths"]["output_dir"] == str(out)
    assert json.loads((out / "provenance.json").read_bytes().decode("utf-8"))[0]["command"]
    assert len(json.loads((out / "provenance.json").read_bytes().decode("utf-8"))) == 2
    assert (out / "heldout.csv").read_text(encoding="utf-8").splitlines() == ["step,iou", "4,0.5"]
    assert (out / "csv" / "metrics.csv").read_text(encoding="utf-8").splitlines() == [
        "heldout/iou,step,train/loss",
        ",0,1.0",
    ]
