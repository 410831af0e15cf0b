"""The ``nlpsf`` command-line contract that other tools call, with the scene options, the impact report and
the field: the same numbers as the library, bad input named."""

from __future__ import annotations

import csv
import io
import json
import subprocess
import sys

import pytest

from nlpsf import cli
from nlpsf.sim import experiment
from nlpsf.sim import scene as scenes
from nlpsf.solve import solver

SIMULATE_FIELDS = {
    "band",
    "sca",
    "magnitude",
    "beta",
    "sigma_beta",
    "realizations",
    "flux_electrons",
    "peak_electrons",
    "reference",
    "dR_over_R",
    "de1",
    "de2",
    "flags",
    "elapsed_s",
}


def run(capsys, *argv):
    code = cli.main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


def test_simulate_json_has_the_contract_fields(capsys):
    code, out, _ = run(
        capsys,
        "simulate",
        "--band",
        "H158",
        "--sca",
        "18",
        "--magnitude",
        "18.3",
        "--beta",
        "5e-7",
        "--realizations",
        "5",
        "--seed",
        "1",
        "--oversampling",
        "3",
        "--stamp",
        "96",
        "--exptime",
        "168.1",
        "--json",
    )
    assert code == 0
    payload = json.loads(out)
    assert set(payload) >= SIMULATE_FIELDS
    assert set(payload["reference"]) >= {"e1", "e2", "sigma"}
    for metric in ("dR_over_R", "de1", "de2"):
        assert set(payload[metric]) == {"mean", "std", "stderr"}
    assert payload["band"] == "H158" and payload["realizations"] == 5
    assert 0.005 < payload["dR_over_R"]["mean"] < 0.05


def test_repeated_magnitudes_and_betas_give_a_list(capsys):
    code, out, _ = run(
        capsys,
        "simulate",
        "--magnitude",
        "19",
        "--magnitude",
        "21",
        "--beta",
        "1e-7",
        "--beta",
        "5e-7",
        "--realizations",
        "3",
        "--json",
    )
    payload = json.loads(out)
    assert code == 0 and isinstance(payload, list) and len(payload) == 4
    assert [(p["magnitude"], p["beta"]) for p in payload] == [(19, 1e-7), (19, 5e-7), (21, 1e-7), (21, 5e-7)]


def test_sigma_beta_std_is_the_spread_over_beta_maps(capsys):
    code, out, _ = run(
        capsys, "simulate", "--magnitude", "19", "--beta", "5e-7", "--sigma-beta", "5e-8", "--realizations", "10", "--json"
    )
    payload = json.loads(out)
    assert code == 0 and payload["sigma_beta"] == 5e-8
    assert payload["dR_over_R"]["std"] > 0
    assert payload["dR_over_R"]["stderr"] == pytest.approx(payload["dR_over_R"]["std"] / 10**0.5)
    assert payload["centroid_offset_fine_pixels"] is not None


def test_slopes_command(capsys):
    code, out, _ = run(capsys, "slopes", "--magnitude", "20", "--realizations", "5", "--method", "linear", "--json")
    payload = json.loads(out)
    assert code == 0 and payload[0]["bias_slope"]["dR_over_R"]["mean"] > 0


def test_readable_table_without_json(capsys):
    # m = 17.5 is just past saturation (m = 18.03): flagged, but the moments still converge.
    code, out, _ = run(capsys, "simulate", "--magnitude", "17.5", "--realizations", "3", "--scene", "paper")
    assert code == 0 and "dR/R" in out and "saturated" in out and "±" in out


def test_every_realization_failing_exits_1(capsys):
    # m = 14 drives 1 - 2 beta Q negative at the core: every adaptive-moment fit fails.
    code, out, err = run(capsys, "simulate", "--magnitude", "14", "--realizations", "3", "--scene", "paper")
    assert code == 1 and "failed in 3 of 3" in out and "every realization" in err


@pytest.mark.parametrize(
    ("argv", "name"),
    [
        (["--band", "Q999"], "--band"),
        (["--sca", "0"], "--sca"),
        (["--sca", "19"], "--sca"),
        (["--magnitude", "nan"], "--magnitude"),
        (["--exptime", "-3"], "--exptime"),
        (["--full-well", "0"], "--full-well"),
        (["--beta", "inf"], "--beta"),
        (["--realizations", "0"], "--realizations"),
        (["--stamp", "4"], "--stamp"),
        (["--sigma-beta=-1e-9"], "--sigma-beta"),
        (["--sigma-beta", "-1e-9"], "--sigma-beta"),
        (["--weight-cut", "-1"], "--weight-cut"),
        (["--beta-convention", "galsim", "--beta", "-2e-3"], "--beta"),
    ],
)
def test_bad_arguments_exit_2_naming_the_option(capsys, argv, name):
    code, out, err = run(capsys, "simulate", *argv, "--json")
    assert code == 2 and out == ""
    # The option the user typed, never the library's internal name (full_well_e, weight_cut_rho2, ...).
    assert f"error: {name}:" in err and "_e:" not in err and "rho2" not in err


def test_console_script_is_installed():
    result = subprocess.run([sys.executable, "-m", "nlpsf", "--version"], capture_output=True, text=True, check=True)
    assert result.stdout.startswith("nlpsf ")
    # Subcommands other modules register are there too.
    listing = subprocess.run([sys.executable, "-m", "nlpsf", "--help"], capture_output=True, text=True, check=True).stdout
    for command in ("simulate", "slopes", "solve", "tables", "tradeoff", "serve"):
        assert command in listing


def test_no_weight_cut_is_valid_json(capsys):
    code, out, _ = run(capsys, "simulate", "--weight-cut", "none", "--realizations", "3", "--json")
    assert code == 0 and json.loads(out)["conditions"]["weight_cut_rho2"] is None


def test_galsim_convention_takes_a_negative_beta(capsys):
    code, out, _ = run(
        capsys, "simulate", "--beta-convention", "galsim", "--beta", "-5e-7", "--magnitude", "19", "--realizations", "3", "--json"
    )
    galsim = json.loads(out)
    code_paper, out_paper, _ = run(capsys, "simulate", "--beta", "5e-7", "--magnitude", "19", "--realizations", "3", "--json")
    paper = json.loads(out_paper)
    assert code == code_paper == 0 and galsim["beta"] == -5e-7 and galsim["beta_paper"] == 5e-7
    assert galsim["dR_over_R"]["mean"] == paper["dR_over_R"]["mean"]


def test_every_option_has_help_and_shows_its_default():
    from nlpsf.cli import COMMANDS, build_parser

    for command in COMMANDS:
        parser, _ = build_parser([command])
        sub = parser._subparsers._group_actions[0].choices[command]
        for action in sub._actions:
            if action.dest in ("help", "tables_command"):
                continue
            assert action.help, f"{command} {action.option_strings} has no help"
        text = sub.format_help()
        if command in ("simulate", "slopes", "solve"):
            assert "(default: H158)" in text and "139.149 s" in text and "168.1 s" in text  # the exposure: the scene's


def test_a_closed_pipe_is_not_a_traceback():
    # `nlpsf tables show | head -1`: the reader goes away after one line.
    script = "import sys; from nlpsf.cli import main; sys.exit(main(['tables', 'show', '--format', 'csv']))"
    producer = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    producer.stdout.readline()
    producer.stdout.close()
    _, err = producer.communicate(timeout=60)
    assert b"Traceback" not in err and b"BrokenPipeError" not in err


def test_throughput_option_picks_the_effective_areas_and_is_named_in_the_conditions(capsys):
    fluxes = {}
    for throughput in ("roman-2024", "galsim-2021"):
        code, out, _ = run(capsys, "simulate", "--sca", "18", "--realizations", "3", "--throughput", throughput, "--json")
        assert code == 0
        payload = json.loads(out)
        assert payload["conditions"]["throughput"] == throughput
        fluxes[throughput] = payload["flux_electrons"]
    # Official SCA 18 F158 zero point 26.457 (Roman_zeropoints_20240301) against GalSim 2021's 26.511.
    assert fluxes["roman-2024"] / fluxes["galsim-2021"] == pytest.approx(10 ** (-0.4 * (26.511 - 26.457)), rel=2e-3)
    with pytest.raises(SystemExit) as refused:
        cli.main(["simulate", "--throughput", "cycle-5"])
    assert refused.value.code == 2 and "--throughput" in capsys.readouterr().err


def test_solve_batch_answers_each_csv_row_on_its_own(capsys, tmp_path):
    import csv
    import io

    from nlpsf.solve.solver import solve

    batch = tmp_path / "requests.csv"
    batch.write_text("band,metric,magnitude,tolerance,precision\nH158,size,18.3,1e-4,\nJ129,e1,,1e-4,0.01\nH158,size,abc,1e-4,\n")
    code, out, err = run(capsys, "solve", "--batch", str(batch), "--scene", "paper")
    assert code == 1 and "1 of 3 rows" in err
    rows = list(csv.DictReader(io.StringIO(out)))
    assert [r["error_field"] for r in rows] == ["", "", "magnitude"]
    paper = solve("H158", magnitude=18.3, tolerance=1e-4, scene="paper")
    assert float(rows[0]["precision"]) == pytest.approx(paper.precision, rel=1e-12)
    expected = solve("J129", metric="e1", tolerance=1e-4, precision=0.01, scene="paper")
    assert rows[1]["solved_for"] == "magnitude" and float(rows[1]["magnitude"]) == pytest.approx(expected.magnitude, rel=1e-12)
    assert rows[1]["binding_limit"] == (expected.binding_limit or "")
    code, out, _ = run(capsys, "solve", "--batch", str(batch), "--json", "--scene", "paper")
    answers = json.loads(out)
    assert [a["ok"] for a in answers] == [True, True, False] and answers[2]["error"]["field"] == "magnitude"


def test_solve_batch_reads_a_spreadsheets_csv_and_refuses_a_file_that_would_swap_values(capsys, tmp_path):
    from nlpsf.solve.solver import solve

    excel = tmp_path / "excel.csv"  # Excel's "CSV UTF-8": a byte-order mark, CRLF, padding columns
    excel.write_bytes(b"\xef\xbb\xbfband,magnitude,tolerance,,\r\nH158,18.3,1e-4,,\r\n")
    code, out, _ = run(capsys, "solve", "--batch", str(excel), "--scene", "paper")
    row = next(csv.DictReader(io.StringIO(out)))
    assert code == 0 and row["band"] == "H158" and row["error"] == ""
    assert float(row["precision"]) == pytest.approx(
        solve("H158", magnitude=18.3, tolerance=1e-4, scene="paper").precision, rel=1e-12
    )
    for text, named in (("band,band,magnitude,tolerance\nH158,J129,18,1e-4\n", "band more than once"),
                        ("band,magnitude,tolerance\nH158,18,1e-4,9\n", "line 2 has 4 cells")):  # fmt: skip
        bad = tmp_path / "bad.csv"
        bad.write_text(text)
        code, out, err = run(capsys, "solve", "--batch", str(bad), "--scene", "paper")
        assert code == 2 and out == "" and "--batch" in err and named in err


@pytest.mark.parametrize("command", ["kernel", "residual"])
@pytest.mark.parametrize(
    "option", [["--over-field"], ["--batch", "rows.csv"], ["--fidelity", "linear"], ["--precision", "0.01"], ["--stars", "4"],
               ["--mode", "scatter"], ["--accuracy", "0.01"], ["--shear-c", "1e-4"]],
)  # fmt: skip
def test_kernel_and_residual_refuse_the_solve_options_they_would_ignore(capsys, command, option):
    # A kernel or a residual's effect is one star's response: an option that asks for more (an answer over
    # the SCA, a batch, a fidelity, stars averaged) would be silently dropped, so it is not offered.
    residual = ["--polynomial", "0,1e-4"] if command == "residual" else []
    with pytest.raises(SystemExit) as refused:
        cli.main([command, "--magnitude", "18", *residual, *option])
    assert refused.value.code == 2 and option[0] in capsys.readouterr().err


def test_residual_does_not_offer_the_kernels_output(capsys):
    with pytest.raises(SystemExit) as refused:
        cli.main(["residual", "--magnitude", "18", "--polynomial", "0,1e-4", "--output", "effect.ecsv"])
    assert refused.value.code == 2 and "--output" in capsys.readouterr().err


def test_save_scene_without_a_change_writes_the_scene_the_answer_used(capsys, tmp_path):
    from nlpsf.request import presets
    from nlpsf.sim import scene as scenes

    ask = ["solve", "--band", "J129", "--sca", "4", "--magnitude", "18.5", "--tolerance", "1e-3", "--json"]
    saved = tmp_path / "default.json"
    code, out, _ = run(capsys, *ask, "--save-scene", str(saved))
    assert code == 0 and saved.exists()
    # Reloaded, it is the same star as observed: the same answer (the Roman default with this SCA's sky).
    code, again, _ = run(capsys, *ask, "--scene", str(saved))
    assert code == 0 and json.loads(again)["precision"] == pytest.approx(json.loads(out)["precision"], rel=1e-12)
    paper = tmp_path / "paper.json"
    assert run(capsys, *ask, "--scene", "paper", "--save-scene", str(paper))[0] == 0
    assert scenes.load(paper) == presets.load_scene("paper")


def test_every_pupil_scale_rule_reaches_the_simulation(capsys):
    # The rule is the optics' (roman.pupil): the simulated size follows the pupil's scale, a larger
    # pupil a smaller PSF. SCA 18's skinny mask: official is 4.3 % larger than galsim, header 5.7 % (their pixel scales).
    sigmas = {}
    for rule in ("galsim", "header", "official"):
        argv = ["simulate", "--band", "H158", "--sca", "18", "--magnitude", "20", "--realizations", "2", "--method", "linear"]
        code, out, _ = run(capsys, *argv, "--pupil-scale", rule, "--json")
        assert code == 0
        got = json.loads(out)
        assert got["conditions"]["pupil_scale"] == rule and got["conditions"]["pupil_scale_source"]
        sigmas[rule] = got["reference"]["sigma"]
    assert sigmas["header"] < sigmas["official"] < sigmas["galsim"]
    with pytest.raises(SystemExit) as refused:
        cli.main(["simulate", "--pupil-scale", "hubble"])
    assert refused.value.code == 2 and "--pupil-scale" in capsys.readouterr().err


def test_cli_simulate_with_scene_options_matches_the_library(capsys):
    code, out, _ = run(
        capsys, "simulate", "--realizations", "4", "--jitter", "0.014", "--ipc", "roman", "--position", "100,200", "--json",
        "--scene", "paper",
    )  # fmt: skip
    assert code == 0
    got = json.loads(out)
    model = scenes.SceneModel(position=(100.0, 200.0), jitter_arcsec=0.014, ipc=scenes.ROMAN_IPC_KERNEL, ipc_label="roman")
    want = experiment.simulate(experiment.SimulationConfig(realizations=4, scene=model), [18.3], [5e-7])[0]
    assert got["dR_over_R"]["mean"] == want.dR_over_R.mean
    assert got["conditions"]["scene"]["effects_on"]["ipc"] is True


def test_cli_nl_coefficients_set_beta_and_higher_orders(capsys, tmp_path):
    saved = tmp_path / "scene.json"
    code, out, _ = run(
        capsys,
        "slopes",
        "--realizations",
        "4",
        "--magnitude",
        "20",
        "--nl-coefficients",
        "4e-7,1e-13",
        "--save-scene",
        str(saved),
        "--method",
        "linear",
        "--json",
    )
    assert code == 0
    got = json.loads(out)[0]
    assert got["beta0"] == 4e-7 and got["conditions"]["scene"]["nl_coefficients"] == [1e-13]
    assert scenes.load(str(saved)).nl_coefficients == (1e-13,)


@pytest.mark.parametrize(
    ("argv", "option"),
    [
        (("--jitter", "-0.1"), "--jitter"),
        (("--sed", "vega"), "--sed"),
        (("--position", "0,10"), "--position"),
        (("--position", "nan,10"), "--position"),
        (("--scene", "nominal"), "--scene"),
        (("--background", "-1"), "--background"),
        (("--bfe", "nan"), "--bfe"),
        (("--nl-coefficients", "5e-7", "--beta", "4e-7"), "--nl-coefficients"),
    ],
)
def test_cli_bad_scene_input_exits_2_naming_the_option(capsys, argv, option):
    code, _, err = run(capsys, "simulate", "--realizations", "2", *argv)
    assert code == 2 and option in err


def test_cli_two_by_two_ipc_file_exits_2(capsys, tmp_path):
    path = tmp_path / "k.txt"
    path.write_text("0 0.01\n0.01 1\n")
    code, _, err = run(capsys, "slopes", "--ipc", str(path))
    assert code == 2 and "--ipc" in err and "3x3" in err


def test_cli_impact_contract(capsys):
    code, out, _ = run(
        capsys,
        "impact",
        "--band",
        "H158",
        "--sca",
        "18",
        "--magnitude",
        "18.3",
        "--realizations",
        "6",
        "--scene",
        "roman",
        "--json",
    )
    assert code == 0
    report = json.loads(out)
    assert [e["name"] for e in report["effects"]] == list(scenes.EFFECTS)
    for effect in report["effects"]:
        assert set(effect["impact"]) == {"size", "e1", "e2", "e"} and isinstance(effect["on"], bool)
        assert "cost_s" in effect
    assert report["conditions"]["scene"]["name"] == "roman"


def test_cli_over_field_and_sca_all(capsys):
    code, out, _ = run(
        capsys, "solve", "--band", "J129", "--sca", "3", "--over-field", "--magnitude", "19", "--tolerance", "1e-4", "--json",
        "--scene", "paper",
    )  # fmt: skip
    assert code == 0
    got = json.loads(out)
    assert len(got["conditions"]["over_field"]) == 5 and got["flag_codes"][0] == "worst_over_field"
    code, _, err = run(capsys, "solve", "--band", "J129", "--sca", "all", "--magnitude", "19", "--tolerance", "1e-4")
    assert code == 2 and "--sca" in err
    # The options the plain solve takes reach the over-field answer too (they were once dropped).
    options = ["--magnitude", "19", "--tolerance", "1e-4", "--mode", "scatter", "--stars", "16", "--throughput", "galsim-2021"]
    code, out, err = run(capsys, "solve", "--band", "J129", "--sca", "3", "--over-field", *options, "--json", "--scene", "paper")
    assert code == 0, err
    got = json.loads(out)
    library = solver.solve_over_field(
        "J129", [3], mode="scatter", stars=16, throughput="galsim-2021", magnitude=19.0, tolerance=1e-4, scene="paper"
    )
    assert got["precision"] == pytest.approx(library.precision, rel=1e-12)
    assert got["conditions"]["throughput"] == "galsim-2021" and got["conditions"]["stars"] == 16
