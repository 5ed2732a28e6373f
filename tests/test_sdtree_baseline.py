"""`python -m guiding sdtree-baseline`: its five tables, with the command that made them, from a tiny run."""

import pandas as pd
import pytest

from guiding.cli import main
from guiding.experiments.sdtree_baseline import PRESET_VARIANTS, SHARE_VARIANTS, THRESHOLD_CONSTANTS, VARIANTS
from guiding.experiments.sdtree_combination import COMBINATION_METHODS, COMBINATIONS


def test_sdtree_baseline_command_writes_its_tables(tmp_path):
    assert main(["sdtree-baseline", "--out", str(tmp_path), "--scene", "cornell", "--scale", "0.05", "--spp", "24",
                 "--seeds", "0,1", "--reference-spp", "16", "--threshold-scales", "0.05,0.07",
                 "--preset-scenes", "cornell:0.05,cornell:0.07", "--variant", "llvm_ad_rgb"]) == 0
    summary = pd.read_csv(tmp_path / "sdtree_baseline.csv")
    assert list(summary["variant"]) == [v.label for v in VARIANTS] and (summary["seeds"] == 2).all()
    assert summary["mae"].notna().all() and summary["mae_vs_first"].iloc[0] == 0
    previous = summary.set_index("variant").loc["sdtree, previous setup"]
    # its one refinement, after the first iteration (8 spp), at the previous threshold 12000·sqrt(8) (CSV: 4 digits)
    assert "combine=last" in previous["overrides"]
    assert previous["last_threshold"] == pytest.approx(12000 * 8 ** 0.5, rel=1e-3)
    threshold = pd.read_csv(tmp_path / "sdtree_threshold.csv")
    assert len(threshold) == 2 * len(THRESHOLD_CONSTANTS) and threshold["resolution"].nunique() == 2
    # the references of the study have the same samples per image at both sizes: 16 spp at 12 x 12, 8 at 17 x 17
    assert list(threshold["reference_spp"].unique()) == [16, 8]
    preset = pd.read_csv(tmp_path / "sdtree_improved_preset.csv")
    assert list(preset["variant"]) == 2 * [v.label for v in PRESET_VARIANTS]
    assert list(preset["scale"].unique()) == [0.05, 0.07]
    assert preset["mae"].notna().all() and (preset["seeds"] == 2).all()
    shares = pd.read_csv(tmp_path / "sdtree_bsdf_share.csv")
    assert list(shares["variant"]) == 2 * [v.label for v in SHARE_VARIANTS]
    assert "bsdf_fraction=0.3" in set(shares["overrides"]) and shares["mae"].notna().all()
    # the break-even cost of a row is (brdf's MAE / its MAE)² on its scene: the cost at which it ties at equal time
    for _, scene in shares.groupby("scale"):
        brdf = scene["mae"].iloc[0]
        assert scene["break_even_cost"].tolist() == pytest.approx(((brdf / scene["mae"]) ** 2).tolist(), rel=5e-3)
    combination = pd.read_csv(tmp_path / "sdtree_combination" / "equal_spp.csv")
    assert len(combination) == 2 * len(COMBINATION_METHODS) * len(COMBINATIONS) and (combination["seeds"] == 2).all()
    # every combination of a render beside its last iteration: that one's difference to itself is 0
    last = combination[combination["combination"] == COMBINATIONS[1]]
    assert (last["mean_minus_last"] == 0).all() and (last["mae_vs_last"] == 0).all()
    assert combination["mae"].notna().all() and combination["reference_se"].gt(0).all()
    for name in ("sdtree_baseline.md", "sdtree_threshold.md", "sdtree_improved_preset.md", "sdtree_bsdf_share.md",
                 "sdtree_combination/equal_spp.md"):
        text = (tmp_path / name).read_text()
        assert "python -m guiding sdtree-baseline --part" in text and "## Runs" in text
    # the references are cached in the harness's layout
    assert (tmp_path / "sdtree_baseline" / "references" / "cornell" / "x0.05-spp16" / "image.exr").exists()


def test_seconds_budget_is_for_the_combination_study_only(tmp_path, capsys):
    assert main(["sdtree-baseline", "--out", str(tmp_path / "out"), "--part", "threshold", "--seconds", "5"]) == 2
    assert "--seconds is for --part combination only" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
