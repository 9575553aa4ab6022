"""The coverage study's command line refuses bad counts before any fit (fitting/study.py)."""

from __future__ import annotations

import pytest

from fitting import study


@pytest.mark.parametrize("args", [["--seeds", "0"], ["--seeds", "9", "--max-seeds", "5"], ["--foreign-seeds", "-1"],
                                  ["--first-seed", "-3"]])
def test_bad_seed_counts_are_refused(tmp_path, capsys, args):
    assert study.main(["--out", str(tmp_path), *args]) == 2
    assert "error:" in capsys.readouterr().err
    assert not (tmp_path / "fits.jsonl").exists()
