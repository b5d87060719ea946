"""benchmarks/presets_report.py: what a preset's row and its note say where its runs are short of
8 of 10, slower than half SB3's, without SB3's side, without a record, or overridden."""

from __future__ import annotations

from types import SimpleNamespace

from test_bench_presets import run


def test_presets_without_sb3_say_why(presets_bench) -> None:
    preset = presets_bench.presets_table.PRESETS["mbrl_pendulum"]
    report = presets_bench.report
    ours = report.Side(preset, [run(presets_bench, 100, [-300, -200, -180], -190.0)])
    cfg = SimpleNamespace(total_frames=30_000)
    row = dict(
        zip(report.HEADERS, report.summary_row(preset, cfg, ours, report.Side(preset, []), "M1"))
    )
    assert row["SB3 solved"] == "SB3 has no model-based RL" and row["solved"] == "1/1"


def test_a_preset_short_of_8_of_10_says_so_in_its_row_and_note(presets_bench) -> None:
    report = presets_bench.report
    preset = presets_bench.presets_table.PRESETS["mbrl_pendulum"]
    short = presets_bench.presets_table.Preset(**{**vars(preset), "short_of": "tried A and B"})
    cfg = SimpleNamespace(total_frames=30_000, eval_episodes=10, eval_every=2_000)
    ours = report.Side(short, [run(presets_bench, 100, [-300, -200, -180], -190.0)])
    ours.runs += [run(presets_bench, 101, [-300, -200, -180], -400.0)]  # its final misses -250
    row = dict(
        zip(report.HEADERS, report.summary_row(short, cfg, ours, report.Side(short, []), "M1"))
    )
    assert row["solved"] == "1/2 (short of 8/10: see its note)"
    none = report.Side(short, [])
    assert "; **short of 8 of 10 held-out seeds**: tried A and B; " in report.note(
        short, cfg, ours, none
    )
    assert "short of" not in report.note(preset, cfg, ours, none)
    # where its runs reach 8 of 10 (another backend's, say), neither row nor note says short
    ours.runs.pop()
    row = report.summary_row(short, cfg, ours, none, "M1")
    assert dict(zip(report.HEADERS, row))["solved"] == "1/1"
    assert "short of" not in report.note(short, cfg, ours, none)
    # what was tried and the checks run after tuning: the note links the tuning log's section
    assert report.note(short, cfg, ours, none).endswith(
        "; what was tried, and seeds run as checks: [docs/tuning.md](docs/tuning.md#mbrl_pendulum)"
    )


def test_a_short_row_of_overridden_runs_points_to_the_presets_own(presets_bench) -> None:
    """In a section of runs with an --override (another backend's), a row short of 8 of 10 is
    flagged whether or not the preset has a note on it, and its note does not tell the
    preset's own runs' story as if of these."""
    report = presets_bench.report
    preset = presets_bench.presets_table.PRESETS["mbrl_pendulum"]
    noted = presets_bench.presets_table.Preset(**{**vars(preset), "short_of": "7 of 10: tried A"})
    cfg = SimpleNamespace(total_frames=30_000, eval_episodes=10, eval_every=2_000)
    ours = [
        run(presets_bench, 100, [-300, -200, -180], -190.0),
        run(presets_bench, 101, [-300] * 3, -400.0),
    ]
    none = report.Side(preset, [])
    for p in (preset, noted):
        side = report.Side(p, ours)
        row = dict(zip(report.HEADERS, report.summary_row(p, cfg, side, none, "M1", own=False)))
        assert row["solved"] == "1/2 (short of 8/10: see its note)", row
        text = report.note(p, cfg, side, none, own=False)
        assert f"**short of 8 of 10 held-out seeds**: {report.OVERRIDDEN_SHORT};" in text
        assert "tried A" not in text
    # the preset's own runs: flagged only where its note says why
    assert "short of" not in report.note(preset, cfg, report.Side(preset, ours), none)


def test_a_section_without_sb3s_side_leaves_its_settings_out_of_the_notes(presets_bench) -> None:
    """A section made without --sb3 (another backend's, say) names no SB3 settings it never
    ran; one with SB3's side names them, for a preset SB3 has not run yet too."""
    report, presets = presets_bench.report, presets_bench.presets_table.PRESETS
    cfg = SimpleNamespace(total_frames=40_000, eval_episodes=10, eval_every=10_000)
    ours = [run(presets_bench, 100, [100, 500, 500, 500], 500.0)]
    both = [presets["dqn_cartpole"], presets["mbrl_pendulum"]]
    configs = {p.experiment: cfg for p in both}

    def notes(runs) -> str:
        return "\n".join(x for x in report.tables(both, configs, runs) if x.startswith("- `"))

    alone = notes(ours)
    assert alone.count("- `") == 2 and "SB3" not in alone, alone
    theirs = [run(presets_bench, 101, [100, 500, 500, 500], 500.0, "SB3", 5.0)]
    beside = notes(ours + theirs)
    assert "SB3: DQN('MlpPolicy'" in beside and "SB3 has no model-based RL" in beside


def test_a_preset_with_no_record_says_left_out_not_0_of_0(presets_bench) -> None:
    """A preset --read-only left out (no record of it as it is now) keeps its row, saying so,
    with no "0/0" solved or reached that reads as a run that solved nothing."""
    report, presets = presets_bench.report, presets_bench.presets_table.PRESETS
    cfg = SimpleNamespace(total_frames=40_000, eval_episodes=10, eval_every=10_000)
    both = [presets["dqn_cartpole"], presets["mbrl_pendulum"]]
    ours = [run(presets_bench, 100, [100, 500, 500, 500], 500.0)]  # dqn_cartpole's only
    rows = [x for x in report.tables(both, {p.experiment: cfg for p in both}, ours) if x]
    table = rows[0].splitlines()
    left = dict(zip(report.HEADERS, table[3].strip("| ").split(" | ")))
    assert left["preset"] == "`mbrl_pendulum`", table
    assert left["solved"] == "no record: left out" and "0/0" not in table[3], table[3]
    ran = dict(zip(report.HEADERS, table[2].strip("| ").split(" | ")))
    assert ran["solved"] == "1/1" and ran["frames to target"].endswith("1/1 reached"), ran


def test_a_time_to_the_target_above_half_sb3s_is_flagged_and_its_note_says_why(
    presets_bench,
) -> None:
    report = presets_bench.report
    preset = presets_bench.presets_table.PRESETS["dqn_cartpole"]
    slow = presets_bench.presets_table.Preset(**{**vars(preset), "slow": "tried C"})
    cfg = SimpleNamespace(total_frames=40_000, eval_episodes=10, eval_every=10_000)
    ours = [run(presets_bench, 100, [100, 500, 500, 500], 500.0)]  # 500 at 20k frames, 8 s
    theirs = [run(presets_bench, 100, [100, 500, 500, 500], 500.0, "SB3", 5.0)]  # 500 at 10 s

    def cell(p) -> str:
        row = report.summary_row(p, cfg, report.Side(p, ours), report.Side(p, theirs), "M1")
        return dict(zip(report.HEADERS, row))["rlpipe/SB3 s to target"]

    def note(p) -> str:
        return report.note(p, cfg, report.Side(p, ours), report.Side(p, theirs))

    assert cell(preset) == "0.80 (above 0.5)"
    assert cell(slow) == "0.80 (above 0.5: see its note)"
    assert "; **time to the target above 0.5× SB3's**: tried C; " in note(slow)
    assert "above" not in note(preset)
    ours[0] = run(presets_bench, 100, [100, 500, 500, 500], 500.0, seconds=2.515)  # 5.03 s to 500
    assert cell(preset) == "0.50 (above 0.5)"  # 0.503: above, though it rounds to 0.50
    assert "tried C" in note(slow)
    ours[0] = run(presets_bench, 100, [100, 500, 500, 500], 500.0, seconds=2.0)  # 4 s: 0.40
    assert cell(slow) == "0.40" and "above" not in note(slow)  # the note explains no more
