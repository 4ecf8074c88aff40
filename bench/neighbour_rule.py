"""Which neighbours, and how many, per view (issue 48, item 2): the data a measured rule is
chosen on, and the rules compared.

For every pair folder (a fitted scene: ``make-pairs`` output with renders of the held-out
views) and every held-out view, with one checkpoint, zero-shot, every stage at its default:

1. the ``--candidates`` nearest training views (the paper's ranking), each measured as the
   enhancer measures it at request time (:func:`roguenerf.enhance.select.measure_candidates`:
   coverage, error of its reprojected photo against the render, consensus with the other
   candidates, angle, baseline);
2. the view enhanced with the first ``n`` candidates for each ``n`` of ``--counts`` (PSNR and
   FLIP gain over the render), with the enhancer's default rule, and with each rule of
   ``--rules`` (:class:`roguenerf.enhance.NeighbourRule` settings by name, :data:`RULES`).

Per view results are cached in ``--cache`` (rerun the same command after a stop). Writes
``OUTPUT.csv`` (one row per view and choice, the candidates' measurements as JSON in
``candidates``), ``OUTPUT.json`` (rows and per pair and choice means) and ``OUTPUT.png`` (mean
gain of each choice per pair), stamped with date, machine and commit.

    .venv/bin/python -m bench.neighbour_rule runs/kinds/pairs/can_clip/hash_s1 ... \\
        --output bench/results/neighbour_rule_choice
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from bench.common import REPO, RESULTS, caption_line, configure_runtime, save_figure, stamp, write_json, write_outputs

RULES = {
    "measured": {"measured": True},
}
"""Named rules (``NeighbourRule`` keyword arguments) compared beside the fixed counts."""


def rules_tag(names: list[str]) -> str:
    """The rules' names and a short hash of their settings and NeighbourRule's defaults (a
    changed default or setting is measured again, not read from the cache)."""
    import dataclasses
    import hashlib

    from roguenerf.enhance import NeighbourRule

    if not names:
        return "none"
    text = json.dumps([[n, dataclasses.asdict(NeighbourRule(**RULES[n]))] for n in names], sort_keys=True)
    return "-".join(names) + "_" + hashlib.sha1(text.encode()).hexdigest()[:8]


def pair_label(folder: Path) -> tuple[str, str]:
    """``(scene, kind)`` of a bench.kinds pair folder ``.../pairs/SCENE/KIND_s1...``."""
    return folder.parent.name, folder.name.split("_s")[0]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("pairs", type=Path, nargs="+", help="pair folders (make-pairs output with held-out renders)")
    p.add_argument("--checkpoint", type=Path, default=None, help="default: the shipped checkpoint")
    p.add_argument("--candidates", type=int, default=6)
    p.add_argument("--counts", type=lambda t: [int(x) for x in t.split(",") if x], default=[1, 2, 3, 4, 5])
    p.add_argument("--rules", type=lambda t: [x for x in t.split(",") if x], default=[],
                   help=f"named rules to compare ({', '.join(RULES)})")
    p.add_argument("--without", type=lambda t: [x for x in t.split(",") if x], default=[],
                   help="also each rule with this stage off (comma-separated of colour, trust, align)")
    p.add_argument("--search", action="store_true",
                   help="instead: PAIRS are OUTPUT.json files of earlier runs; replay every setting of the "
                        "measured rule on them (the choice half) and write the ranking to OUTPUT.json")
    p.add_argument("--figure", action="store_true",
                   help="instead: PAIRS are OUTPUT.json files of earlier runs; write the broad figure (per pair "
                        "and half: fixed counts, the default, the measured rule --rule replayed)")
    p.add_argument("--rule", default="{}", help="--figure: the measured rule's setting as JSON (choose's keywords)")
    p.add_argument("--choice", type=lambda t: [x for x in t.split(",") if x], default=[],
                   help="--figure: the scenes the rule was chosen on (the rest are the report half)")
    p.add_argument("--max-views", type=int, default=None)
    p.add_argument("--cache", type=Path, default=REPO / "runs" / "neighbour_rule")
    p.add_argument("--output", type=Path, default=RESULTS / "neighbour_rule")
    args = p.parse_args(argv)
    for folder in args.pairs:
        if args.search or args.figure:
            if not folder.is_file():
                p.error(f"{folder}: not a file (--search and --figure read OUTPUT.json files)")
        elif not (folder / "transforms.json").is_file():
            p.error(f"{folder}: not a pair folder (no transforms.json)")
    if any(x not in ("colour", "trust", "align") for x in args.without):
        p.error(f"--without: expected some of colour, trust, align, got {args.without}")
    unknown = [r for r in args.rules if r not in RULES]
    if unknown:
        p.error(f"--rules: unknown {unknown} (expected some of {', '.join(RULES)})")
    return args


def measure_view(enhancer, scene, i: int, args, checkpoint_name: str) -> list[dict]:
    """Rows of one held-out view: every choice's gain, the candidates' measurements."""
    from roguenerf.enhance import EnhanceOptions, NeighbourRule
    from roguenerf.inference import SceneEnhancer
    from roguenerf.metrics import flip, psnr

    frame = scene.frames[i]
    render, depth, photo = scene.render(i), scene.depth(i), scene.photo(i)
    K, pose = frame.K, frame.world_from_cam
    base_psnr, base_flip = float(psnr(render, photo)), float(flip(render, photo))
    positions = enhancer.candidates(pose, args.candidates)
    start = time.perf_counter()
    measured = enhancer.measure(render, depth, K, pose, positions)
    measure_seconds = time.perf_counter() - start
    names = [enhancer.train_names[p] for p in positions]
    rows = []

    def row(choice: str, result) -> None:
        rows.append({"view": frame.name, "choice": choice, "neighbours": json.dumps(result.neighbours),
                     "count": len(result.neighbours), "render_psnr": round(base_psnr, 4),
                     "gain_db": round(float(psnr(result.image, photo)) - base_psnr, 4),
                     "render_flip": round(base_flip, 5),
                     "flip_change": round(float(flip(result.image, photo)) - base_flip, 5),
                     "seconds": round(result.seconds, 3), "measure_seconds": round(measure_seconds, 3),
                     "candidates": json.dumps([{"name": n, **c.as_dict()} for n, c in zip(names, measured)])})

    for n in args.counts:
        first = [enhancer.train[p] for p in positions[:n]]
        row(f"first {n}", enhancer.enhance(render, depth, K, pose, neighbours=first))
    row("default", enhancer.enhance(render, depth, K, pose))

    def sibling(options):  # another rule or stage setting, sharing the caches
        other = SceneEnhancer(scene, enhancer.model, options=options)
        other._small, other._tiny, other._sources, other._depths = (enhancer._small, enhancer._tiny,
                                                                    enhancer._sources, enhancer._depths)
        return other

    for stage in args.without:
        row(f"default, no {stage}", sibling(EnhanceOptions().with_(**{stage: None})).enhance(render, depth, K, pose))
    for name in args.rules:
        rule = NeighbourRule(**RULES[name])
        row(name, sibling(EnhanceOptions(neighbours=rule)).enhance(render, depth, K, pose))
        for stage in args.without:
            row(f"{name}, no {stage}", sibling(EnhanceOptions(neighbours=rule).with_(**{stage: None}))
                .enhance(render, depth, K, pose))
    return [{"checkpoint": checkpoint_name, **r} for r in rows]


def prefix_gains(rows: list[dict]) -> dict[tuple, dict[int, float]]:
    """Per (scene, kind, view): the gain with the first n candidates, for each measured n."""
    out: dict[tuple, dict[int, float]] = {}
    for r in rows:
        if r["choice"].startswith("first "):
            out.setdefault((r["scene"], r["kind"], r["view"]), {})[int(r["choice"].split()[1])] = r["gain_db"]
    return out


def search(rows: list[dict], grid: dict[str, list]) -> list[dict]:
    """Every setting of the measured rule in ``grid`` (NeighbourRule fields) replayed on the
    rows' views from their cached measurements and prefix gains: per setting, the mean gain
    over the (scene, kind) pairs, the worst pair, and on how many pairs it is at least as good
    as the best fixed count (a setting that picks a non-prefix set on some view is skipped)."""
    import itertools

    from roguenerf.enhance.select import Candidate, choose

    gains = prefix_gains(rows)
    cands: dict[tuple, list[Candidate]] = {}
    for r in rows:
        key = (r["scene"], r["kind"], r["view"])
        if key not in cands:
            cands[key] = [Candidate(position=c["rank"], rank=c["rank"], angle=c["angle"], baseline=c["baseline"],
                                    coverage=c["coverage"], error=c["error"], consensus=c["consensus"])
                          for c in json.loads(r["candidates"])]
    pairs = sorted({k[:2] for k in gains})
    counts = sorted(set.intersection(*(set(g) for g in gains.values())))

    def pair_means(pick) -> dict[tuple, float] | None:
        per: dict[tuple, list[float]] = {}
        for key, g in gains.items():
            n = pick(key)
            if n is None or n not in g:
                return None
            per.setdefault(key[:2], []).append(g[n])
        return {p: sum(v) / len(v) for p, v in per.items()}

    fixed = {n: pair_means(lambda key, n=n: n) for n in counts}
    best_n = max(counts, key=lambda n: sum(fixed[n].values()))
    out = [{"rule": f"fixed {n}", **_score(fixed[n], fixed[best_n], pairs)} for n in counts]
    oracle = pair_means(lambda key: max(gains[key], key=gains[key].get))  # needs the photo: a bound
    out.append({"rule": "oracle: best count per view (needs the photo)", **_score(oracle, fixed[best_n], pairs)})
    names = list(grid)
    for values in itertools.product(*(grid[k] for k in names)):
        setting = dict(zip(names, values, strict=True))
        if not setting["least"] <= setting["most"]:
            continue

        def pick(key, setting=setting):
            chosen = choose(cands[key], **setting)
            ranks = [c.rank for c in chosen]
            return len(ranks) if ranks == list(range(len(ranks))) else None

        means = pair_means(pick)
        if means is not None:
            out.append({"rule": json.dumps(setting), **_score(means, fixed[best_n], pairs)})
    return sorted(out, key=lambda r: -r["mean_gain_db"])


def replay_rule(rows: list[dict], setting: dict) -> list[dict]:
    """The measured rule with ``setting`` (NeighbourRule fields of :func:`choose`) replayed on
    each view from its cached measurements: a row per view as the bench would have measured it
    (choice ``"measured"``: the "first n" row of the count it picks; the rule keeps the paper's
    order, so its choice is always such a prefix unless a candidate sees too little)."""
    from roguenerf.enhance.select import Candidate, choose

    by_view: dict[tuple, dict[str, dict]] = {}
    for r in rows:
        by_view.setdefault((r["scene"], r["kind"], r["view"]), {})[r["choice"]] = r
    out = []
    for choices in by_view.values():
        any_row = next(iter(choices.values()))
        cands = [Candidate(position=c["rank"], rank=c["rank"], angle=c["angle"], baseline=c["baseline"],
                           coverage=c["coverage"], error=c["error"], consensus=c["consensus"])
                 for c in json.loads(any_row["candidates"])]
        ranks = [c.rank for c in choose(cands, **setting)]
        if ranks != list(range(len(ranks))) or f"first {len(ranks)}" not in choices:
            raise SystemExit(f"{any_row['scene']} {any_row['kind']} {any_row['view']}: the rule picks {ranks}, "
                             "not a measured prefix; run the bench with --rules measured instead")
        out.append({**choices[f"first {len(ranks)}"], "choice": "measured"})
    return out


def figure(rows: list[dict], setting: dict, choice_scenes: list[str]) -> tuple[list[dict], list[dict]]:
    """Per (scene, kind) pair and choice: mean gain, worst view, FLIP, the neighbours' measured
    reprojection (the nearest candidate's error and coverage, mean over the views), and which
    half the pair is in (``choice``: the rule was chosen on it; ``report``: it was not); and
    per half and choice: the mean over pairs, the worst pair, and how many pairs the rule
    matches or beats the best fixed count on."""
    rows = rows + replay_rule(rows, setting)
    everywhere = set.intersection(*({r["choice"] for r in rows if (r["scene"], r["kind"]) == key}
                                    for key in {(r["scene"], r["kind"]) for r in rows}))
    rows = [r for r in rows if r["choice"] in everywhere]  # choices some pairs lack (counts 1, 5) left out
    pairs = []
    for m in summary(rows):
        views = [r for r in rows if (r["scene"], r["kind"], r["choice"]) == (m["scene"], m["kind"], m["choice"])]
        nearest = [json.loads(r["candidates"])[0] for r in views]
        pairs.append({**{k: v for k, v in views[0].items() if k in ("date", "machine", "commit", "checkpoint")},
                      "half": "choice" if m["scene"] in choice_scenes else "report", **m,
                      "render_psnr": round(sum(r["render_psnr"] for r in views) / len(views), 3),
                      "nearest_error": round(sum(c["error"] for c in nearest) / len(nearest), 5),
                      "nearest_coverage": round(sum(c["coverage"] for c in nearest) / len(nearest), 4)})
    halves = []
    for half in ("choice", "report"):
        mine = [p for p in pairs if p["half"] == half]
        if not mine:
            continue
        fixed = [c for c in dict.fromkeys(p["choice"] for p in mine) if c.startswith("first ")]
        mean = {c: sum(p["gain_db"] for p in mine if p["choice"] == c) / sum(p["choice"] == c for p in mine)
                for c in dict.fromkeys(p["choice"] for p in mine)}
        best = max(fixed, key=mean.get)
        gain = {(p["scene"], p["kind"], p["choice"]): p["gain_db"] for p in mine}
        for c in mean:
            own = [p for p in mine if p["choice"] == c]
            halves.append({"half": half, "choice": c, "pairs": len(own), "mean_gain_db": round(mean[c], 4),
                           "worst_pair_db": min(p["gain_db"] for p in own),
                           "worst_view_db": min(p["worst_view_gain_db"] for p in own),
                           "pairs_below_zero": sum(p["gain_db"] < 0 for p in own),
                           "views_flip_better": sum(p["views_flip_better"] for p in own),
                           "views": sum(p["views"] for p in own), "best_fixed": best,
                           "pairs_at_least_best_fixed": sum(p["gain_db"] >= gain[(p["scene"], p["kind"], best)] - 1e-9
                                                            for p in own)})
    return pairs, halves


def plot_figure(pairs: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    choices = [c for c in ("first 2", "first 3", "first 4", "default", "measured")
               if any(p["choice"] == c for p in pairs)]
    keys = list(dict.fromkeys((p["half"], p["scene"], p["kind"]) for p in sorted(pairs, key=lambda p: p["half"])))
    fig, ax = plt.subplots(figsize=(max(7, 1.1 * len(keys)), 4.2))
    width = 0.8 / len(choices)
    for c, choice in enumerate(choices):
        gains = [next((p["gain_db"] for p in pairs
                       if (p["half"], p["scene"], p["kind"]) == k and p["choice"] == choice), float("nan"))
                 for k in keys]
        ax.bar([k + c * width for k in range(len(keys))], gains, width, label=choice)
    ax.set_xticks([k + 0.4 - width / 2 for k in range(len(keys))], [f"{h}\n{s}\n{k}" for h, s, k in keys], fontsize=7)
    ax.axhline(0, color="grey", lw=0.8)
    ax.set_ylabel("mean PSNR gain of the held-out views (dB), zero-shot", fontsize=8)
    ax.legend(fontsize=7, ncol=len(choices))
    r = pairs[0]
    fig.suptitle(f"neighbours per view: fixed counts, the default, the measured rule | {r['checkpoint']} | "
                 f"{r['machine'][:50]} | {r['commit']} | {r['date'][:10]}", fontsize=7)
    return save_figure(fig, path)


def _score(means: dict, best: dict, pairs: list) -> dict:
    return {"mean_gain_db": round(sum(means.values()) / len(means), 4),
            "worst_pair_db": round(min(means.values()), 4),
            "pairs_at_least_best_fixed": sum(means[p] >= best[p] - 1e-9 for p in pairs), "pairs": len(pairs)}


def summary(rows: list[dict]) -> list[dict]:
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["scene"], r["kind"], r["choice"]), []).append(r)
    out = []
    for (scene, kind, choice), rs in groups.items():
        n = len(rs)
        out.append({"scene": scene, "kind": kind, "choice": choice, "views": n,
                    "gain_db": round(sum(r["gain_db"] for r in rs) / n, 4),
                    "worst_view_gain_db": min(r["gain_db"] for r in rs),
                    "flip_change": round(sum(r["flip_change"] for r in rs) / n, 5),
                    "views_flip_better": sum(r["flip_change"] < 0 for r in rs),
                    "mean_count": round(sum(r["count"] for r in rs) / n, 2),
                    "seconds": round(sum(r["seconds"] for r in rs) / n, 3)})
    return out


def plot(rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    means = summary(rows)
    choices = list(dict.fromkeys(m["choice"] for m in means))
    pairs = list(dict.fromkeys((m["scene"], m["kind"]) for m in means))
    fig, ax = plt.subplots(figsize=(max(6, 1.2 * len(pairs)), 4))
    width = 0.8 / max(1, len(choices))
    for c, choice in enumerate(choices):
        gains = [next((m["gain_db"] for m in means if (m["scene"], m["kind"]) == pair and m["choice"] == choice),
                      float("nan")) for pair in pairs]
        ax.bar([k + c * width for k in range(len(pairs))], gains, width, label=choice)
    ax.set_xticks([k + 0.4 - width / 2 for k in range(len(pairs))], [f"{s}\n{k}" for s, k in pairs], fontsize=7)
    ax.axhline(0, color="grey", lw=0.8)
    ax.set_ylabel("mean PSNR gain over the renders (dB), zero-shot", fontsize=8)
    ax.legend(fontsize=7, ncol=2)
    caption_line(fig, rows, "neighbour choice per view | {checkpoint}")
    return save_figure(fig, path)


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.figure:
        rows = [r for path in args.pairs for r in json.loads(path.read_text())["rows"]]
        setting = json.loads(args.rule)
        pairs, halves = figure(rows, setting, args.choice)
        write_outputs(args.output, pairs, plot_figure)
        write_json(args.output.with_suffix(".json"), {**stamp(), "rule": setting, "choice_scenes": args.choice,
                                                      "halves": halves, "pairs": pairs})
        for h in halves:
            print(f"{h['half']:>6} {h['choice']:>22}: mean {h['mean_gain_db']:+.3f} dB, worst pair "
                  f"{h['worst_pair_db']:+.3f}, worst view {h['worst_view_db']:+.3f}, FLIP better on "
                  f"{h['views_flip_better']}/{h['views']} views, >= {h['best_fixed']} on "
                  f"{h['pairs_at_least_best_fixed']}/{h['pairs']} pairs")
        return 0
    if args.search:
        rows = [r for path in args.pairs for r in json.loads(path.read_text())["rows"]]
        grid = {"least": [1, 2, 3], "most": [2, 3, 4], "min_coverage": [0.0, 0.2, 0.4],
                "error_ratio": [1.0, 1.1, 1.25, 1.5, 2.0, 100.0], "near_degrees": [0.0, 2.0, 4.0, 6.0]}
        table = search(rows, grid)
        write_json(args.output.with_suffix(".json"), {**stamp(), "grid": grid, "table": table})
        for r in table[:25]:
            print(f"{r['mean_gain_db']:+.3f} dB (worst pair {r['worst_pair_db']:+.3f}), "
                  f"{r['pairs_at_least_best_fixed']}/{r['pairs']} pairs >= best fixed: {r['rule']}")
        return 0
    from tqdm import tqdm

    from roguenerf.checkpoint import default_checkpoint_path, load_checkpoint
    from roguenerf.data.readers import load_scene
    from roguenerf.imageio import atomic_write
    from roguenerf.inference import SceneEnhancer

    configure_runtime()
    checkpoint = args.checkpoint or default_checkpoint_path()
    model, _ = load_checkpoint(checkpoint)
    base = stamp()
    rows: list[dict] = []
    for folder in args.pairs:
        scene_name, kind = pair_label(folder)
        scene = load_scene(folder)
        enhancer = SceneEnhancer(scene, model)
        views = scene.indices("test")[: args.max_views]
        tag = (f"{checkpoint.stem}_c{args.candidates}_n{'-'.join(map(str, args.counts))}"
               f"_{rules_tag(args.rules)}_without{'-'.join(args.without) or 'none'}")
        for i in tqdm(views, desc=f"{scene_name} ({kind})", unit="view"):
            path = args.cache / scene_name / kind / tag / f"{scene.frames[i].name}.json"
            if path.is_file():
                view_rows = json.loads(path.read_text())
            else:
                view_rows = measure_view(enhancer, scene, i, args, checkpoint.name)
                atomic_write(path, json.dumps(view_rows).encode(), make_parents=True)
            rows += [{**base, "scene": scene_name, "kind": kind, **r} for r in view_rows]
    write_outputs(args.output, rows, plot)
    write_json(args.output.with_suffix(".json"), {"rows": rows, "summary": summary(rows)})
    for m in summary(rows):
        print(f"{m['scene']:>12} {m['kind']:>6} {m['choice']:>10}: {m['gain_db']:+.3f} dB "
              f"(worst {m['worst_view_gain_db']:+.3f}), FLIP {m['flip_change']:+.4f}, {m['mean_count']} neighbours")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
