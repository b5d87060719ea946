"""benchmarks/presets.py: the held-out protocol, the solved rule, the table's figures on runs made
up by hand and BENCHMARKS.md's section replacement (the command line: test_bench_presets_cli.py)."""

from __future__ import annotations

import dataclasses
import re
import threading
from functools import partial
from pathlib import Path
from types import SimpleNamespace

import pytest

from rlpipe.errors import RlpipeError


def test_seeds_read_as_runs(presets_bench) -> None:
    seed_text = presets_bench.report.seed_text
    assert seed_text(range(100, 110)) == "100–109"
    assert seed_text([*range(90, 100), *range(10)]) == "0–9, 90–99"
    assert seed_text([9, 1, 5, 6, 7]) == "1, 5–7, 9" and seed_text([3, 4]) == "3, 4"
    assert seed_text([]) == "–"


def test_published_runs_default_to_the_held_out_seeds(presets_bench) -> None:
    table = presets_bench.presets_table
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
def test_the_protocol_refuses(presets_bench, seeds, tune, overrides, message) -> None:
    preset = presets_bench.presets_table.PRESETS["dqn_cartpole"]
    with pytest.raises(RlpipeError, match=None) as refused:
        presets_bench.presets_table.seeds_for([preset], seeds, tune, overrides)
    assert message in str(refused.value) and "\n" not in str(refused.value)


def test_tuning_runs_take_seeds_below_100_or_from_1000(presets_bench) -> None:
    preset = presets_bench.presets_table.PRESETS["dqn_cartpole"]
    seeds = presets_bench.presets_table.seeds_for([preset], [2, 0, 2, 1000], True, ["algo.lr=1e-3"])
    assert seeds == {"dqn_cartpole": (2, 0, 1000)}


def run(presets_bench, seed, means, final, which="rlpipe", seconds=4.0):
    evals = [(10_000 * (i + 1), m, seconds * (i + 1)) for i, m in enumerate(means)]
    return presets_bench.presets_runs.Run("dqn_cartpole", seed, which, evals, final, machine="box")


def test_solved_needs_the_last_three_evals_and_the_final_eval(presets_bench) -> None:
    assert run(presets_bench, 100, [100, 500, 500, 500], 500.0).solved(500)
    assert not run(presets_bench, 100, [500, 480, 500, 500], 500.0).solved(500)  # last three: 493.3
    assert not run(presets_bench, 100, [500, 500, 500], 499.0).solved(500)  # the final eval below
    assert not run(presets_bench, 100, [500, 500, 500], None).solved(500)  # no final eval


def test_only_the_runs_that_run_get_a_line(presets_bench, capsys) -> None:
    """A benchmark resumed or remade with --read-only reads hundreds of records back: no line
    each, but one for each run that ran, and for a record that could not be read."""
    Run = presets_bench.presets_runs.Run

    def broken() -> object:
        raise ValueError("torn record")

    scheduler = presets_bench.presets_runs.Scheduler(1, 3, read_back=2)
    scheduler.group([("p", 100, "rlpipe", partial(Run, "p", 100, "rlpipe", [], 1.0), True)])
    scheduler.group([("p", 101, "rlpipe", broken, True)])
    scheduler.group([("p", 100, "SB3", partial(Run, "p", 100, "SB3", [], 1.0), False)])
    scheduler.results()
    lines = sorted(capsys.readouterr().err.splitlines(), key=lambda line: "SB3" in line)
    assert len(lines) == 2, lines
    assert lines[0].startswith("presets: p seed 101 rlpipe FAILED (ValueError: torn record)")
    assert lines[1].startswith("presets: p seed 100 SB3 done in 0 s (1/1 runs, ")


def test_a_finished_run_read_back_holds_no_slot(presets_bench) -> None:
    """Resuming a half-run benchmark: each seed's rlpipe record is done, SB3's side runs. With
    two slots the SB3 runs of two seeds overlap; a done run taking a slot would make them wait."""
    second_started, Run = threading.Event(), presets_bench.presets_runs.Run

    def first() -> object:  # final 0: the second seed's run never started beside this one
        return Run("p", 100, "SB3", [], float(second_started.wait(timeout=5)))

    def second() -> object:
        second_started.set()
        return Run("p", 101, "SB3", [], 1.0)

    scheduler = presets_bench.presets_runs.Scheduler(2, 4)
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


def test_a_machine_is_one_label_whatever_the_days_its_runs_ran_on(presets_bench) -> None:
    runs = [run(presets_bench, 100 + i, [1.0], 1.0) for i in range(3)]
    days = ["2026-11-26 · box, 2 cores", "2026-11-27 · box, 2 cores", "2026-11-26 · big, 16 cores"]
    for r, m in zip(runs, days):
        r.machine = m
    assert list(presets_bench.report.machines(runs).values()) == ["M1", "M1", "M2"]
    assert presets_bench.report.legend(runs) == [
        "- M1: box, 2 cores (runs of 2026-11-26, 2026-11-27)",
        "- M2: big, 16 cores (runs of 2026-11-26)",
    ]


def test_a_record_names_its_cpu_as_well_as_its_cores(presets_bench) -> None:
    cpuinfo = (
        "processor\t: 0\ncpu family\t: 6\nmodel\t\t: 167\nmodel name\t: Intel(R) Xeon(R) "
        "Processor\nflags\t\t: fpu sse4_2 avx avx2 avx512f\n\nprocessor\t: 1\nmodel\t\t: 99\n"
    )
    named = "Intel(R) Xeon(R) Processor (family 6, model 167, avx512)"
    assert presets_bench.common.cpu_model(cpuinfo) == named
    older = cpuinfo.replace(" avx512f", "").replace("167", "63")
    assert presets_bench.common.cpu_model(older) == named.replace("167", "63").replace(
        "avx512", "avx2"
    )
    assert presets_bench.common.cpu_model("") != ""  # no /proc/cpuinfo fields: what platform knows
    assert presets_bench.common.cpu_model() in presets_bench.common.machine(["torch"])


def test_a_seed_row_names_sb3_s_machine_where_it_ran_elsewhere(presets_bench) -> None:
    preset = presets_bench.presets_table.PRESETS["dqn_cartpole"]
    ours = [run(presets_bench, 100, [500.0], 500.0), run(presets_bench, 101, [500.0], 500.0)]
    theirs = [
        run(presets_bench, 100, [500.0], 500.0, "SB3"),
        run(presets_bench, 101, [500.0], 500.0, "SB3"),
    ]
    theirs[1].machine = "small"
    label = presets_bench.report.machines(ours + theirs)
    sides = (presets_bench.report.Side(preset, ours), presets_bench.report.Side(preset, theirs))
    rows = presets_bench.report.detail_rows(preset, *sides, label)
    assert [row[-1] for row in rows] == ["M1", "M1 (SB3: M2)"]
    # seconds are compared on one machine only: seed 101's pair is left out of the ratio
    ours[0].evals, theirs[0].evals = [(10_000, 500.0, 2.0)], [(10_000, 500.0, 8.0)]
    ours[1].evals, theirs[1].evals = [(10_000, 500.0, 1.0)], [(10_000, 500.0, 100.0)]
    assert presets_bench.report.ratio(*sides, lambda r: r.evals[0][2])[0] == "0.25"
    theirs[0].machine = "small"
    assert presets_bench.report.ratio(*sides, lambda r: r.evals[0][2])[0] == "– (on other machines)"


def test_a_ratio_over_runs_of_different_days_says_so(presets_bench) -> None:
    """A side re-run alone (its records replaced, the other's kept) is still compared on one
    machine, but the ratio is no longer from one run: the cell says so."""
    preset = presets_bench.presets_table.PRESETS["dqn_cartpole"]
    ours, theirs = (
        [run(presets_bench, 100, [500.0], 500.0)],
        [run(presets_bench, 100, [500.0], 500.0, "SB3")],
    )
    ours[0].evals, theirs[0].evals = [(10_000, 500.0, 2.0)], [(10_000, 500.0, 8.0)]
    sides = (presets_bench.report.Side(preset, ours), presets_bench.report.Side(preset, theirs))
    ours[0].machine = theirs[0].machine = "2026-11-26 · box, 2 cores"
    assert presets_bench.report.ratio(*sides, lambda r: r.evals[0][2])[0] == "0.25"
    ours[0].machine = "2026-11-28 · box, 2 cores"
    assert presets_bench.report.ratio(*sides, lambda r: r.evals[0][2]) == (
        "0.25 (runs on different days)",
        0.25,
    )
    # the tables say what the mark means, whether or not a record carries the ‡ of old starts
    cfg = SimpleNamespace(total_frames=10_000, eval_episodes=20, eval_every=5_000)
    text = "\n".join(presets_bench.report.tables([preset], {"dqn_cartpole": cfg}, ours + theirs))
    assert presets_bench.report.DAYS_NOTE in text and "‡" not in text
    ours[0].machine = theirs[0].machine
    text = "\n".join(presets_bench.report.tables([preset], {"dqn_cartpole": cfg}, ours + theirs))
    assert "runs on different days" not in text


def test_the_row_of_a_preset(presets_bench) -> None:
    # without its note on falling short: the row's own cells, not the mark the note adds
    preset = dataclasses.replace(presets_bench.presets_table.PRESETS["dqn_cartpole"], short_of="")
    report = presets_bench.report
    ours = report.Side(
        preset,
        [
            run(presets_bench, 100, [200, 500, 500, 500], 500.0),  # solved; 500 at 20k frames, 8 s
            run(
                presets_bench, 101, [500, 480, 500, 500], 500.0
            ),  # 500 at 10k, 4 s; last three 493.3
            run(presets_bench, 102, [100, 200, 500, 500], 480.0),  # 500 at 30k, 12 s; final below
        ],
    )
    theirs = report.Side(
        preset,
        [
            run(
                presets_bench, 100, [100, 200, 500, 500], 500.0, "SB3", 8.0
            ),  # 500 at 24 s; last three 400
            run(presets_bench, 101, [500, 500, 500, 500], 500.0, "SB3", 8.0),  # 500 at 8 s
            run(presets_bench, 102, [100, 100, 100, 100], 100.0, "SB3", 8.0),
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


def test_the_tuning_log_has_a_section_for_every_preset(presets_bench) -> None:
    """Each note links ``docs/tuning.md#<preset>``: the page holds that heading for every
    preset of presets.yaml, and none for a preset that is not there."""
    page = Path(__file__).resolve().parents[1] / presets_bench.report.TUNING_LOG
    headings = re.findall(r"^## `(\w+)`$", page.read_text(), re.M)
    assert sorted(headings) == sorted(presets_bench.presets_table.PRESETS), headings


def test_a_record_from_before_a_config_field_existed_still_stands_at_its_default(
    presets_bench,
) -> None:
    from rlpipe.cli import compose_run

    runs = presets_bench.presets_runs
    cfg = compose_run("+experiment=dqn_cartpole")
    saved = runs.identity(cfg)
    assert runs.same_identity(saved, cfg)
    older = {k: v for k, v in saved.items() if k != "algo.eps_zeta"}  # before the field
    assert runs.same_identity(older, cfg)  # the new field at its default: the same run
    assert not runs.same_identity(older, compose_run("+experiment=dqn_cartpole", "algo.eps_zeta=2"))
    assert not runs.same_identity({**saved, "algo.lr": 1.0}, cfg)
    assert not runs.same_identity({**saved, "algo.gone": 1}, cfg)  # a field since removed


def test_a_record_on_another_backend_stands_only_where_the_backend_is_auto(presets_bench, tmp_path):
    import json

    from rlpipe.cli import compose_run

    runs, cfg = presets_bench.presets_runs, compose_run("+experiment=ppo_cartpole")
    saved = {"evals": [[10_000, 500.0, 1.0]], "final": 500.0, "config": runs.identity(cfg)}
    (tmp_path / "rlpipe.json").write_text(json.dumps({**saved, "backend": "envpool"}))
    backends = ("auto", "gymnasium", "envpool")
    on = {b: compose_run("+experiment=ppo_cartpole", f"env.backend={b}") for b in backends}
    assert runs.rlpipe_finished(tmp_path, on["auto"])  # auto picks per machine: the record says
    assert runs.rlpipe_finished(tmp_path, on["envpool"])
    assert not runs.rlpipe_finished(tmp_path, on["gymnasium"])  # run anew on gymnasium


def test_a_record_on_envpool_is_stale_where_auto_now_takes_gymnasium_for_one_copy(
    presets_bench, tmp_path
):
    import json

    from rlpipe.cli import compose_run

    runs, cfg = presets_bench.presets_runs, compose_run("+experiment=sac_mountaincar_continuous")
    saved = {"evals": [[5_000, 90.0, 1.0]], "final": 95.0, "config": runs.identity(cfg)}
    (tmp_path / "rlpipe.json").write_text(json.dumps({**saved, "backend": "envpool"}))
    assert not runs.rlpipe_finished(tmp_path, cfg)  # run anew: auto takes gymnasium for it
    pinned = compose_run("+experiment=sac_mountaincar_continuous", "env.backend=envpool")
    assert runs.rlpipe_finished(tmp_path, pinned)
    (tmp_path / "rlpipe.json").write_text(json.dumps({**saved, "backend": "gymnasium"}))
    assert runs.rlpipe_finished(tmp_path, cfg)


def test_the_aggregate_is_normalised_by_the_target(presets_bench) -> None:
    table, report = presets_bench.presets_table, presets_bench.report
    cartpole, pendulum = table.PRESETS["dqn_cartpole"], table.PRESETS["sac_pendulum"]
    assert cartpole.normalised(500.0) == 1.0 and cartpole.normalised(cartpole.floor) == 0.0
    assert pendulum.normalised(-157.0) == 1.0 and pendulum.normalised(-150.0) > 1.0
    sides = [
        report.Side(cartpole, [run(presets_bench, s, [500] * 3, 500.0) for s in (100, 101)]),
        report.Side(pendulum, [run(presets_bench, s, [-157] * 3, -157.0) for s in (100, 101)]),
    ]
    assert report.aggregate(sides).startswith("IQM 1.00 [1.00, 1.00] over 2 preset(s), 4 run(s)")


def test_a_section_replaces_its_own_and_keeps_the_rest(presets_bench, tmp_path) -> None:
    page = tmp_path / "BENCHMARKS.md"
    page.write_text("# Benchmarks\n\nindex\n\n## A (benchmarks/a.py)\n\nold a\n## B (x)\n\nb\n")
    presets_bench.common.replace_section(page, "## A (benchmarks/a.py)\n\nnew a\n")
    presets_bench.common.replace_section(page, "## C (benchmarks/c.py)\n\nc\n")
    assert page.read_text() == (
        "# Benchmarks\n\nindex\n\n## A (benchmarks/a.py)\n\nnew a\n\n## B (x)\n\nb\n\n"
        "## C (benchmarks/c.py)\n\nc\n"
    )
