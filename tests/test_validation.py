"""The equal-spp learning table's summary over seeds (its renders replaced by fixed rows)."""

import pytest

from guiding.experiments import validation


def test_learning_table_reports_the_mean_and_standard_error_over_seeds(monkeypatch):
    maes = {("brdf", 1): 0.20, ("brdf", 2): 0.24, ("ours", 1): 0.10, ("ours", 2): 0.11, ("ours", 3): 0.12}

    def rows(scene_name, scale, spp, reference_spp, seeds, configurations):
        return [{**fields, "seed": seed, "spp": spp, "mae": maes[(method, seed)], "relmse": 1.0, "hit_rate": 0.5,
                 "seconds": float(seed), "update_seconds": 0.0, "refined_bins": 0}
                for fields, method, _ in configurations for seed in seeds if (method, seed) in maes]

    monkeypatch.setattr(validation, "_equal_spp_rows", rows)
    table = validation.learning_table(methods=("ours", "brdf"), seeds=(1, 2, 3)).set_index("method")
    assert list(table.index) == ["ours", "brdf"]        # the methods' order, not sorted
    assert table.loc["ours", "mae"] == pytest.approx(0.11)
    assert table.loc["ours", "mae_se"] == pytest.approx(0.01 / 3 ** 0.5)     # sample std 0.01 over 3 seeds
    assert table.loc["brdf", "mae_se"] == pytest.approx(0.02)     # sample std 0.02·√2 over 2 seeds
    assert table.loc["ours", "seconds"] == pytest.approx(2.0)
    assert table["seeds"].tolist() == [3, 2]      # the renders each row averages
    assert table.loc["ours", "spp"] == 256 and table["spp"].dtype.kind == "i"
    one = validation.learning_table(methods=("ours",), seeds=(1,))
    assert one["mae_se"].isna().all()                   # one render: its spread is unknown, not zero
