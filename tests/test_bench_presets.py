"""benchmarks/presets.py: the held-out protocol, the solved rule, the table's figures on runs made
up by hand and BENCHMARKS.md's section replacement (the command line: test_bench_presets_cli.py)."""

from __future__ import annotations

import dataclasses
import importlib
import re
import threading
from functools import partial
from pathlib import Path
from types import SimpleNamespace

import pytest
from conftest import benchmarks_importable

from rlpipe.errors import RlpipeError


@pytest.fixture(scope="module")
def bench():
    with benchmarks_importable():
        yield SimpleNamespace(
            **{m: importlib.import_module(m) for m in ("common", "presets_runs", "presets_table")},
            report=importlib.import_module("presets_report"),
        )


def test_seeds_read_as_runs(bench) -> None:
    seed_text = bench.report.seed_text
    assert seed_text(range(100, 110)) == "100–109"
    assert seed_text([*range(90, 100), *range(10)]) == "0–9, 90–99"
    assert seed_text([9, 1, 5, 6, 7]) == "1, 5–7, 9" and seed_text([3, 4]) == "3, 4"
    assert seed_text([]) == "–"


def test_published_runs_default_to_the_held_out_seeds(bench) -> None:
    table = bench.presets_table
    chosen = [table.PRESETS["dqn_cartpole"], table.PRESETS["sac_bipedal"]]
    seeds = table.seeds_for(chosen, None, tune=False, overrides=[])
    assert seeds == {"dqn_cartpole": tuple(range(100, 110)), "sac_bipedal": (100, 101, 102)}
    assert table.seeds_for(chosen, [101], False, ["env.backend=gymnasium"])["sac_bipedal"] == (101,)
    assert not {s for p in table.PRESETS.values() for s in p.tuned_on} & set(table.RESERVED)


@pytest.mark.parametrize(
    "seeds, tune, overrides, message",
    [
        ([0, 1, 100], True, [], "--tune refuses held-out seeds (100)"),
        ([1000, 999, 110], True, [], "--tune refuses held-out seeds (110, 999)"),
        (None, True, [], "--tune needs --seeds"),
        ([0], False, [], "seed(s) 0: not dqn_cartpole's held-out seeds"),
        ([105], False, ["algo.lr=1e-3"], "--override algo.lr=1e-3 changes the preset"),
    ],
)
def test_the_protocol_refuses(bench, seeds, tune, overrides, message) -> None:
    preset = bench.presets_table.PRESETS["dqn_cartpole"]
    with pytest.raises(RlpipeError, match=None) as refused:
        bench.presets_table.seeds_for([preset], seeds, tune, overrides)
    assert message in str(refused.value) and "\n" not in str(refused.value)


def test_tuning_runs_take_seeds_below_100_or_from_1000(bench) -> None:
    preset = bench.presets_table.PRESETS["dqn_cartpole"]
    seeds = bench.presets_table.seeds_for([preset], [2, 0, 2, 1000], True, ["algo.lr=1e-3"])
    assert seeds == {"dqn_cartpole": (2, 0, 1000)}


def run(bench, seed, means, final, which="rlpipe", seconds=4.0):
    evals = [(10_000 * (i + 1), m, seconds * (i + 1)) for i, m in enumerate(means)]
    return bench.presets_runs.Run("dqn_cartpole", seed, which, evals, final, machine="box")


def test_solved_needs_the_last_three_evals_and_the_final_eval(bench) -> None:
    assert run(bench, 100, [100, 500, 500, 500], 500.0).solved(500)
    assert not run(bench, 100, [500, 480, 500, 500], 500.0).solved(500)  # last three: 493.3
    assert not run(bench, 100, [500, 500, 500], 499.0).solved(500)  # the final eval below
    assert not run(bench, 100, [500, 500, 500], None).solved(500)  # no final eval


def test_only_the_runs_that_run_get_a_line(bench, capsys) -> None:
    """A benchmark resumed or remade with --read-only reads hundreds of records back: no line
    each, but one for each run that ran, and for a record that could not be read."""
    Run = bench.presets_runs.Run

    def broken() -> object:
        raise ValueError("torn record")

    scheduler = bench.presets_runs.Scheduler(1, 3, read_back=2)
    scheduler.group([("p", 100, "rlpipe", partial(Run, "p", 100, "rlpipe", [], 1.0), True)])
    scheduler.group([("p", 101, "rlpipe", broken, True)])
    scheduler.group([("p", 100, "SB3", partial(Run, "p", 100, "SB3", [], 1.0), False)])
    scheduler.results()
    lines = sorted(capsys.readouterr().err.splitlines(), key=lambda line: "SB3" in line)
    assert len(lines) == 2, lines
    assert lines[0].startswith("presets: p seed 101 rlpipe FAILED (ValueError: torn record)")
    assert lines[1].startswith("presets: p seed 100 SB3 done in 0 s (1/1 runs, ")


def test_a_finished_run_read_back_holds_no_slot(bench) -> None:
    """Resuming a half-run benchmark: each seed's rlpipe record is done, SB3's side runs. With
    two slots the SB3 runs of two seeds overlap; a done run taking a slot would make them wait."""
    second_started, Run = threading.Event(), bench.presets_runs.Run

    def first() -> object:  # final 0: the second seed's run never started beside this one
        return Run("p", 100, "SB3", [], float(second_started.wait(timeout=5)))

    def second() -> object:
        second_started.set()
        return Run("p", 101, "SB3", [], 1.0)

    scheduler = bench.presets_runs.Scheduler(2, 4)
    for seed, job in ((100, first), (101, second)):
        read_back = partial(Run, "p", seed, "rlpipe", [], 2.0)
        scheduler.group([("p", seed, "rlpipe", read_back, True), ("p", seed, "SB3", job, False)])
    runs = scheduler.results()
    assert [(r.seed, r.which, r.final) for r in runs] == [
        (100, "rlpipe", 2.0),
        (100, "SB3", 1.0),
        (101, "rlpipe", 2.0),
        (101, "SB3", 1.0),
    ]


def test_a_machine_is_one_label_whatever_the_days_its_runs_ran_on(bench) -> None:
    runs = [run(bench, 100 + i, [1.0], 1.0) for i in range(3)]
    days = ["2026-11-26 · box, 2 cores", "2026-11-27 · box, 2 cores", "2026-11-26 · big, 16 cores"]
    for r, m in zip(runs, days):
        r.machine = m
    assert list(bench.report.machines(runs).values()) == ["M1", "M1", "M2"]
    assert bench.report.legend(runs) == [
        "- M1: box, 2 cores (runs of 2026-11-26, 2026-11-27)",
        "- M2: big, 16 cores (runs of 2026-11-26)",
    ]


def test_a_record_names_its_cpu_as_well_as_its_cores(bench) -> None:
    cpuinfo = (
        "processor\t: 0\ncpu family\t: 6\nmodel\t\t: 167\nmodel name\t: Intel(R) Xeon(R) "
        "Processor\nflags\t\t: fpu sse4_2 avx avx2 avx512f\n\nprocessor\t: 1\nmodel\t\t: 99\n"
    )
    named = "Intel(R) Xeon(R) Processor (family 6, model 167, avx512)"
    assert bench.common.cpu_model(cpuinfo) == named
    older = cpuinfo.replace(" avx512f", "").replace("167", "63")
    assert bench.common.cpu_model(older) == named.replace("167", "63").replace("avx512", "avx2")
    assert bench.common.cpu_model("") != ""  # no /proc/cpuinfo fields: what platform knows
    assert bench.common.cpu_model() in bench.common.machine(["torch"])


def test_a_seed_row_names_sb3_s_machine_where_it_ran_elsewhere(bench) -> None:
    preset = bench.presets_table.PRESETS["dqn_cartpole"]
    ours = [run(bench, 100, [500.0], 500.0), run(bench, 101, [500.0], 500.0)]
    theirs = [run(bench, 100, [500.0], 500.0, "SB3"), run(bench, 101, [500.0], 500.0, "SB3")]
    theirs[1].machine = "small"
    label = bench.report.machines(ours + theirs)
    sides = (bench.report.Side(preset, ours), bench.report.Side(preset, theirs))
    rows = bench.report.detail_rows(preset, *sides, label)
    assert [row[-1] for row in rows] == ["M1", "M1 (SB3: M2)"]
    # seconds are compared on one machine only: seed 101's pair is left out of the ratio
    ours[0].evals, theirs[0].evals = [(10_000, 500.0, 2.0)], [(10_000, 500.0, 8.0)]
    ours[1].evals, theirs[1].evals = [(10_000, 500.0, 1.0)], [(10_000, 500.0, 100.0)]
    assert bench.report.ratio(*sides, lambda r: r.evals[0][2])[0] == "0.25"
    theirs[0].machine = "small"
    assert bench.report.ratio(*sides, lambda r: r.evals[0][2])[0] == "– (on other machines)"


def test_a_ratio_over_runs_of_different_days_says_so(bench) -> None:
    """A side re-run alone (its records replaced, the other's kept) is still compared on one
    machine, but the ratio is no longer from one run: the cell says so."""
    preset = bench.presets_table.PRESETS["dqn_cartpole"]
    ours, theirs = [run(bench, 100, [500.0], 500.0)], [run(bench, 100, [500.0], 500.0, "SB3")]
    ours[0].evals, theirs[0].evals = [(10_000, 500.0, 2.0)], [(10_000, 500.0, 8.0)]
    sides = (bench.report.Side(preset, ours), bench.report.Side(preset, theirs))
    ours[0].machine = theirs[0].machine = "2026-11-26 · box, 2 cores"
    assert bench.report.ratio(*sides, lambda r: r.evals[0][2])[0] == "0.25"
    ours[0].machine = "2026-11-28 · box, 2 cores"
    assert bench.report.ratio(*sides, lambda r: r.evals[0][2]) == (
        "0.25 (runs on different days)",
        0.25,
    )
    # the tables say what the mark means, whether or not a record carries the ‡ of old starts
    cfg = SimpleNamespace(total_frames=10_000, eval_episodes=20, eval_every=5_000)
    text = "\n".join(bench.report.tables([preset], {"dqn_cartpole": cfg}, ours + theirs))
    assert bench.report.DAYS_NOTE in text and "‡" not in text
    ours[0].machine = theirs[0].machine
    text = "\n".join(bench.report.tables([preset], {"dqn_cartpole": cfg}, ours + theirs))
    assert "runs on different days" not in text


def test_the_row_of_a_preset(bench) -> None:
    # without its note on falling short: the row's own cells, not the mark the note adds
    preset = dataclasses.replace(bench.presets_table.PRESETS["dqn_cartpole"], short_of="")
    report = bench.report
    ours = report.Side(
        preset,
        [
            run(bench, 100, [200, 500, 500, 500], 500.0),  # solved; 500 at 20k frames, 8 s
            run(bench, 101, [500, 480, 500, 500], 500.0),  # 500 at 10k, 4 s; last three 493.3
            run(bench, 102, [100, 200, 500, 500], 480.0),  # 500 at 30k, 12 s; final below
        ],
    )
    theirs = report.Side(
        preset,
        [
            run(bench, 100, [100, 200, 500, 500], 500.0, "SB3", 8.0),  # 500 at 24 s; last three 400
            run(bench, 101, [500, 500, 500, 500], 500.0, "SB3", 8.0),  # 500 at 8 s
            run(bench, 102, [100, 100, 100, 100], 100.0, "SB3", 8.0),
        ],
    )
    cfg = SimpleNamespace(total_frames=40_000)
    row = dict(zip(report.HEADERS, report.summary_row(preset, cfg, ours, theirs, "M1")))
    assert row["seeds"] == "100–102" and row["solved"] == "1/3" and row["SB3 solved"] == "1/3"
    assert row["frames to target"] == "20,000 (10,000–30,000), 3/3 reached"
    assert row["train s to target"] == "8.0 (4.0–12.0)"
    assert row["final: IQM [95% CI]"] == "493.3 [480.0, 500.0]"  # three runs: nothing cut
    assert row["SB3 train s to target"] == "16.0 (8.0–24.0)"
    assert row["rlpipe/SB3 s to target"] == "0.42"  # median of 8/24 and 4/8
    assert row["rlpipe/SB3 s, whole run"] == "0.50"  # 16 s against 32 s on every seed
    assert row["budget (frames)"] == "40,000" and row["machine"] == "M1"


def test_presets_without_sb3_say_why(bench) -> None:
    preset = bench.presets_table.PRESETS["mbrl_pendulum"]
    report = bench.report
    ours = report.Side(preset, [run(bench, 100, [-300, -200, -180], -190.0)])
    cfg = SimpleNamespace(total_frames=30_000)
    row = dict(
        zip(report.HEADERS, report.summary_row(preset, cfg, ours, report.Side(preset, []), "M1"))
    )
    assert row["SB3 solved"] == "SB3 has no model-based RL" and row["solved"] == "1/1"


def test_a_preset_short_of_8_of_10_says_so_in_its_row_and_note(bench) -> None:
    report = bench.report
    preset = bench.presets_table.PRESETS["mbrl_pendulum"]
    short = bench.presets_table.Preset(**{**vars(preset), "short_of": "tried A and B"})
    cfg = SimpleNamespace(total_frames=30_000, eval_episodes=10, eval_every=2_000)
    ours = report.Side(short, [run(bench, 100, [-300, -200, -180], -190.0)])
    ours.runs += [run(bench, 101, [-300, -200, -180], -400.0)]  # its final misses -250
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


def test_the_tuning_log_has_a_section_for_every_preset(bench) -> None:
    """Each note links ``docs/tuning.md#<preset>``: the page holds that heading for every
    preset of presets.yaml, and none for a preset that is not there."""
    page = Path(__file__).resolve().parents[1] / bench.report.TUNING_LOG
    headings = re.findall(r"^## `(\w+)`$", page.read_text(), re.M)
    assert sorted(headings) == sorted(bench.presets_table.PRESETS), headings


def test_a_section_without_sb3s_side_leaves_its_settings_out_of_the_notes(bench) -> None:
    """A section made without --sb3 (another backend's, say) names no SB3 settings it never
    ran; one with SB3's side names them, for a preset SB3 has not run yet too."""
    report, presets = bench.report, bench.presets_table.PRESETS
    cfg = SimpleNamespace(total_frames=40_000, eval_episodes=10, eval_every=10_000)
    ours = [run(bench, 100, [100, 500, 500, 500], 500.0)]
    both = [presets["dqn_cartpole"], presets["mbrl_pendulum"]]
    configs = {p.experiment: cfg for p in both}

    def notes(runs) -> str:
        return "\n".join(x for x in report.tables(both, configs, runs) if x.startswith("- `"))

    alone = notes(ours)
    assert alone.count("- `") == 2 and "SB3" not in alone, alone
    theirs = [run(bench, 101, [100, 500, 500, 500], 500.0, "SB3", 5.0)]
    beside = notes(ours + theirs)
    assert "SB3: DQN('MlpPolicy'" in beside and "SB3 has no model-based RL" in beside


def test_a_preset_with_no_record_says_left_out_not_0_of_0(bench) -> None:
    """A preset --read-only left out (no record of it as it is now) keeps its row, saying so,
    with no "0/0" solved or reached that reads as a run that solved nothing."""
    report, presets = bench.report, bench.presets_table.PRESETS
    cfg = SimpleNamespace(total_frames=40_000, eval_episodes=10, eval_every=10_000)
    both = [presets["dqn_cartpole"], presets["mbrl_pendulum"]]
    ours = [run(bench, 100, [100, 500, 500, 500], 500.0)]  # dqn_cartpole's only
    rows = [x for x in report.tables(both, {p.experiment: cfg for p in both}, ours) if x]
    table = rows[0].splitlines()
    left = dict(zip(report.HEADERS, table[3].strip("| ").split(" | ")))
    assert left["preset"] == "`mbrl_pendulum`", table
    assert left["solved"] == "no record: left out" and "0/0" not in table[3], table[3]
    ran = dict(zip(report.HEADERS, table[2].strip("| ").split(" | ")))
    assert ran["solved"] == "1/1" and ran["frames to target"].endswith("1/1 reached"), ran


def test_a_time_to_the_target_above_half_sb3s_is_flagged_and_its_note_says_why(bench) -> None:
    report = bench.report
    preset = bench.presets_table.PRESETS["dqn_cartpole"]
    slow = bench.presets_table.Preset(**{**vars(preset), "slow": "tried C"})
    cfg = SimpleNamespace(total_frames=40_000, eval_episodes=10, eval_every=10_000)
    ours = [run(bench, 100, [100, 500, 500, 500], 500.0)]  # 500 at 20k frames, 8 s
    theirs = [run(bench, 100, [100, 500, 500, 500], 500.0, "SB3", 5.0)]  # 500 at 10 s

    def cell(p) -> str:
        row = report.summary_row(p, cfg, report.Side(p, ours), report.Side(p, theirs), "M1")
        return dict(zip(report.HEADERS, row))["rlpipe/SB3 s to target"]

    def note(p) -> str:
        return report.note(p, cfg, report.Side(p, ours), report.Side(p, theirs))

    assert cell(preset) == "0.80 (above 0.5)"
    assert cell(slow) == "0.80 (above 0.5: see its note)"
    assert "; **time to the target above 0.5× SB3's**: tried C; " in note(slow)
    assert "above" not in note(preset)
    ours[0] = run(bench, 100, [100, 500, 500, 500], 500.0, seconds=2.515)  # 5.03 s to 500
    assert cell(preset) == "0.50 (above 0.5)"  # 0.503: above, though it rounds to 0.50
    assert "tried C" in note(slow)
    ours[0] = run(bench, 100, [100, 500, 500, 500], 500.0, seconds=2.0)  # 4 s: 0.40
    assert cell(slow) == "0.40" and "above" not in note(slow)  # the note explains no more


def test_a_record_from_before_a_config_field_existed_still_stands_at_its_default(bench) -> None:
    from rlpipe.cli import compose_run

    runs = bench.presets_runs
    cfg = compose_run("+experiment=dqn_cartpole")
    saved = runs.identity(cfg)
    assert runs.same_identity(saved, cfg)
    older = {k: v for k, v in saved.items() if k != "algo.eps_zeta"}  # before the field
    assert runs.same_identity(older, cfg)  # the new field at its default: the same run
    assert not runs.same_identity(older, compose_run("+experiment=dqn_cartpole", "algo.eps_zeta=2"))
    assert not runs.same_identity({**saved, "algo.lr": 1.0}, cfg)
    assert not runs.same_identity({**saved, "algo.gone": 1}, cfg)  # a field since removed


def test_a_record_on_another_backend_stands_only_where_the_backend_is_auto(bench, tmp_path):
    import json

    from rlpipe.cli import compose_run

    runs, cfg = bench.presets_runs, compose_run("+experiment=ppo_cartpole")
    saved = {"evals": [[10_000, 500.0, 1.0]], "final": 500.0, "config": runs.identity(cfg)}
    (tmp_path / "rlpipe.json").write_text(json.dumps({**saved, "backend": "envpool"}))
    backends = ("auto", "gymnasium", "envpool")
    on = {b: compose_run("+experiment=ppo_cartpole", f"env.backend={b}") for b in backends}
    assert runs.rlpipe_finished(tmp_path, on["auto"])  # auto picks per machine: the record says
    assert runs.rlpipe_finished(tmp_path, on["envpool"])
    assert not runs.rlpipe_finished(tmp_path, on["gymnasium"])  # run anew on gymnasium


def test_a_record_on_envpool_is_stale_where_auto_now_takes_gymnasium_for_one_copy(bench, tmp_path):
    import json

    from rlpipe.cli import compose_run

    runs, cfg = bench.presets_runs, compose_run("+experiment=sac_mountaincar_continuous")
    saved = {"evals": [[5_000, 90.0, 1.0]], "final": 95.0, "config": runs.identity(cfg)}
    (tmp_path / "rlpipe.json").write_text(json.dumps({**saved, "backend": "envpool"}))
    assert not runs.rlpipe_finished(tmp_path, cfg)  # run anew: auto takes gymnasium for it
    pinned = compose_run("+experiment=sac_mountaincar_continuous", "env.backend=envpool")
    assert runs.rlpipe_finished(tmp_path, pinned)
    (tmp_path / "rlpipe.json").write_text(json.dumps({**saved, "backend": "gymnasium"}))
    assert runs.rlpipe_finished(tmp_path, cfg)


def test_the_aggregate_is_normalised_by_the_target(bench) -> None:
    table, report = bench.presets_table, bench.report
    cartpole, pendulum = table.PRESETS["dqn_cartpole"], table.PRESETS["sac_pendulum"]
    assert cartpole.normalised(500.0) == 1.0 and cartpole.normalised(cartpole.floor) == 0.0
    assert pendulum.normalised(-157.0) == 1.0 and pendulum.normalised(-150.0) > 1.0
    sides = [
        report.Side(cartpole, [run(bench, s, [500] * 3, 500.0) for s in (100, 101)]),
        report.Side(pendulum, [run(bench, s, [-157] * 3, -157.0) for s in (100, 101)]),
    ]
    assert report.aggregate(sides).startswith("IQM 1.00 [1.00, 1.00] over 2 preset(s), 4 run(s)")


def test_a_section_replaces_its_own_and_keeps_the_rest(bench, tmp_path) -> None:
    page = tmp_path / "BENCHMARKS.md"
    page.write_text("# Benchmarks\n\nindex\n\n## A (benchmarks/a.py)\n\nold a\n## B (x)\n\nb\n")
    bench.common.replace_section(page, "## A (benchmarks/a.py)\n\nnew a\n")
    bench.common.replace_section(page, "## C (benchmarks/c.py)\n\nc\n")
    assert page.read_text() == (
        "# Benchmarks\n\nindex\n\n## A (benchmarks/a.py)\n\nnew a\n\n## B (x)\n\nb\n\n"
        "## C (benchmarks/c.py)\n\nc\n"
    )
