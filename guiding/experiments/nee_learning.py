"""What a guide should learn when the path loop does next-event estimation: the full incident radiance its sampled
directions bring back (``learn_nee_light`` true), or only the share of emission that emitter sampling leaves to
them (false). Equal-spp MAE against a Mitsuba ``path`` reference, several seeds, for the grid and the tree guides.

    python -m guiding.experiments.nee_learning --out results/nee_learning
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

#: (scene, scale): a light seen through a gap, a Cornell box, rough plastic lit indirectly, a sunlit room.
SCENES = (("door-ajar", 0.125), ("cornell-box", 0.125), ("glossy-room", 0.125), ("sun-blinds", 0.0625))
METHODS = ("ours", "ours-plus", "sdtree")
SEEDS = (0, 1, 2)
SPP = 256
REFERENCE_SPP = 8192


def measure(scenes=SCENES, methods=METHODS, seeds=SEEDS, spp: int = SPP, reference_spp: int = REFERENCE_SPP,
            progress=print) -> pd.DataFrame:
    import mitsuba as mi

    from guiding.guides.methods import make_guide
    from guiding.metrics import mae_tonemapped
    from guiding.render.integrator import GuidedPathIntegrator
    from guiding.render.progressive import Budget, render
    from guiding.scenes import load_scene

    rows = []
    for scene_name, scale in scenes:
        scene = load_scene(scene_name, scale)
        reference = render(scene, mi.load_dict({"type": "path", "max_depth": 16}),
                           Budget(spp=reference_spp, pass_spp=256), seed=1000, progress=False).image
        for method in methods:
            for learns_nee_light in (True, False):
                for seed in seeds:
                    props = mi.Properties()
                    props["nee"] = True
                    props["learn_nee_light"] = learns_nee_light
                    integrator = GuidedPathIntegrator(props, guide=make_guide(method))
                    image = render(scene, integrator, Budget(spp=spp), seed=seed, progress=False).image
                    rows.append({"scene": scene_name, "method": method, "learn_nee_light": learns_nee_light,
                                 "seed": seed, "mae": mae_tonemapped(image, reference),
                                 "mean_ratio": float(image.mean() / reference.mean())})
                    progress(rows[-1])
    return pd.DataFrame(rows)


def summary(frame: pd.DataFrame) -> pd.DataFrame:
    """Mean MAE (and its standard deviation over the seeds) per scene and method for both choices, and the ratio of
    the means (< 1: learning only NEE's remainder wins)."""
    table = frame.pivot_table(index=["scene", "method"], columns="learn_nee_light", values="mae", aggfunc=["mean", "std"])
    table.columns = [f"{'mae' if stat == 'mean' else 'mae_std'}_{'full_radiance' if full else 'nee_remainder'}"
                     for stat, full in table.columns]
    table["remainder_over_full"] = table["mae_nee_remainder"] / table["mae_full_radiance"]
    return table.reset_index()


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("results/nee_learning"))
    parser.add_argument("--threads", type=int, default=None)
    args = parser.parse_args(argv)
    from guiding.backend import set_variant

    set_variant("llvm_ad_rgb", args.threads)
    frame = measure()
    args.out.mkdir(parents=True, exist_ok=True)
    frame.to_csv(args.out / "runs.csv", index=False)
    table = summary(frame)
    table.to_csv(args.out / "summary.csv", index=False)
    (args.out / "summary.md").write_text(table.to_markdown(index=False, floatfmt=".4f") + "\n")
    print(table.to_markdown(index=False, floatfmt=".4f"))


if __name__ == "__main__":
    main()
