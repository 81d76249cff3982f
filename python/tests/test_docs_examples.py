"""The examples of docs/model-file.md that users copy, checked against the code that reads them (as
core/calibration_file_test.cc checks the calibration file's example)."""

import re
from pathlib import Path

import pytest

import trackcal

MODEL_FILE_MD = Path(__file__).resolve().parents[2] / "docs" / "model-file.md"
PYTHON_MD = Path(__file__).resolve().parents[2] / "docs" / "python.md"


def fenced_blocks(text, language):
    return re.findall(r"^```" + language + r"\n(.*?)^```$", text, flags=re.M | re.S)


def test_model_file_reference_example_parses():
    """The reference example at the top lists every key; each must be one the parser accepts."""
    blocks = fenced_blocks(MODEL_FILE_MD.read_text(), "yaml")
    assert blocks, "docs/model-file.md has no yaml example"
    info = trackcal._core.parse_model(blocks[0])
    assert info["terms"] == ["physical", "polynomial", "local"]  # one physical chain; the lut is named


def test_adding_a_term_type_registers_a_name_that_is_free():
    """The snippet of "Adding a term type" registered "dipole", a built-in type: copied, it throws
    (TermRegistry::Register refuses a taken name). Its type name must be one the parser does not
    know yet."""
    text = MODEL_FILE_MD.read_text()
    section = text[text.index("## Adding a term type"):]
    snippet = fenced_blocks(section, "cpp")[0]
    match = re.search(r'Register\("([^"]+)"', snippet)
    assert match, snippet
    name = match.group(1)
    with pytest.raises(ValueError, match=f"unknown term type '{name}'"):
        trackcal._core.parse_model(f"terms:\n  - type: {name}\n")


def test_demo_usage_names_a_command_that_runs(capsys):
    """The main job's --help (README: `python -m trackcal.demo`, options with `--help`) printed
    `usage: trackcal demo ...`, and `trackcal` has no `demo` command: the usage line a user copies
    must name a command that runs."""
    import shlex
    import subprocess

    from trackcal import demo

    with pytest.raises(SystemExit) as exit_info:
        demo._main(["--help"])
    assert exit_info.value.code == 0
    match = re.match(r"usage: (.*?) \[-h\]", capsys.readouterr().out)
    assert match, "no usage line"
    result = subprocess.run(shlex.split(match.group(1)) + ["--help"], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0, (match.group(1), result.stderr)
    assert "--max-steps" in result.stdout


def test_the_status_counts_example_runs_as_written(tmp_path, monkeypatch):
    """docs/python.md's status example used names it never defined (cal, positions,
    quaternions_xyzw) and printed counts nobody could reproduce. It now starts from the capture and
    model the text above it gives: run it as written, in that folder."""
    import ast
    import contextlib
    import io
    import subprocess
    import shutil

    text = PYTHON_MD.read_text()
    section = text[text.index("## Correcting poses and the status of a model inverse"):]
    snippet = fenced_blocks(section, "python")[0]
    simulate = re.search(r"`(trackcal-simulate [^`]+)`", section).group(1).split()
    exe = shutil.which(simulate[0])
    assert exe, "trackcal-simulate must be on PATH (scripts/build.sh installs it into the venv)"
    subprocess.run([exe] + simulate[1:], cwd=tmp_path, check=True, capture_output=True)
    (tmp_path / "model.yaml").write_text("terms:\n  - type: dipole\n  - {type: polynomial, degree: 3}\n")
    monkeypatch.chdir(tmp_path)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(snippet, "docs/python.md", "exec"), {})
    counts = ast.literal_eval(out.getvalue().strip())
    documented = ast.literal_eval(re.search(r"# (\{.*\})", snippet).group(1))
    assert set(counts) == set(documented) == {"converged", "ambiguous", "not_converged"}
    assert sum(counts.values()) == sum(documented.values())  # every station of the capture
    # The example shows what the status is for: stations near the toolbox come out ambiguous. The
    # exact count may move by a station or two with the solver's arithmetic on another machine.
    assert counts["ambiguous"] > 0 and abs(counts["ambiguous"] - documented["ambiguous"]) <= 5, counts
