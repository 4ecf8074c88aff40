"""What the stage-setting bench tests share (test_bench_colour, test_bench_trust)."""

from __future__ import annotations

from bench import stage_settings


def summary_by_setting(rows: list[dict], stage: str) -> dict[str, dict]:
    """:func:`bench.stage_settings.summary` of the rows its CSV holds (``gain_db`` and
    ``flip_change`` read back as numbers), by setting."""
    numbers = [{**r, "gain_db": float(r["gain_db"]), "flip_change": float(r["flip_change"])} for r in rows]
    column = stage_settings.STAGES[stage].column
    return {x[column]: x for x in stage_settings.summary(numbers, stage)}
