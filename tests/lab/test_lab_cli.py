"""The lab's entry point (`python -m lab ...`): every command reaches its
module, every report's paths are declared as the `dcdi` verbs' are, and the
reproduction configs: one per shipped network file, each naming existing
scene recipes and lenses, their steps printed by a dry run that runs
nothing, and a finished step skipped on the next run."""
import argparse
import json
import subprocess
import sys
from pathlib import Path

import pytest

from dcdi_core.cli.files import NOT_PATHS, leaves
from dcdi_core.optics.lens import load_lens
from lab import cli, reproduce
from scenes.recipes import RECIPES

ROOT = Path(__file__).resolve().parents[2]
WEIGHTS = ROOT / "dcdi_core" / "models" / "weights"


# ------------------------------------------------------------------ the entry point
def test_every_command_has_its_module_and_main():
    for name, (module, _) in cli.MODULES.items():
        assert callable(__import__(f"lab.{module}", fromlist=["main"]).main), name
    text = cli.build_parser().format_help()
    for name in (*cli.MODULES, "report"):
        assert name in text


def test_every_report_declares_every_option_that_names_a_path():
    verbs = list(leaves(cli.build_parser()))
    assert {words[1] for words, _ in verbs if words[0] == "report"} == set(cli.SPECS)
    for words, parser in verbs:
        if words[0] != "report":
            continue
        spec = cli.SPECS[words[1]]
        declared = set(spec.reads) | set(spec.writes) | set(spec.into)
        dests = {a.dest for a in parser._actions if not isinstance(a, argparse._HelpAction)}
        assert not dests - declared - NOT_PATHS - cli.NOT_PATHS - set(spec.others), words
        assert not declared - dests, words


def test_a_report_refuses_a_bad_lens_in_one_line(tmp_path, capsys):
    out = tmp_path / "out"
    assert cli.main(["report", "simulation-accuracy", "--lens", str(tmp_path / "none.toml"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("lab: error:") and "\n" not in err and "none.toml" in err
    assert not out.exists()


def test_python_m_lab_runs_from_the_root():
    r = subprocess.run([sys.executable, "-m", "lab", "reproduce", "--list"], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert all(name in r.stdout for name in reproduce.config_names())


# ------------------------------------------------------------------ the configs
def test_every_shipped_network_file_has_one_config():
    made = {}
    for name in reproduce.config_names():
        cfg = reproduce.load_config(name)
        if "weights" in cfg:
            assert cfg["weights"] not in made, f"{cfg['weights']}: {made.get(cfg['weights'])} and {name}"
            made[cfg["weights"]] = name
    assert set(made) == {p.name for p in WEIGHTS.glob("*.npz")}
    assert len(made) >= 7


@pytest.mark.parametrize("name", reproduce.config_names())
def test_a_config_names_existing_recipes_lenses_and_folders(name, tmp_path):
    cfg = reproduce.load_config(name)
    frames = {f["folder"] for f in cfg.get("frames", [])}
    for f in cfg.get("frames", []):
        assert f["recipe"] in RECIPES and f["count"] >= 1
        load_lens(f.get("lens", reproduce.FACTORY_LENS))
    for p in cfg.get("pairs", []):
        load_lens(p["lens"])
        assert set(p["frames"]) <= frames, p
    made = frames | {p["folder"] for p in cfg.get("pairs", [])}
    for t in cfg["train"]:
        for lens in ([t["lens"]] if isinstance(t.get("lens"), str) else t.get("lens", [])):
            load_lens(lens)
        for key in ("train", "test", "val", "data"):
            named = t.get(key, [])
            assert set([named] if isinstance(named, str) else named) <= made, (key, named)
    if "weights" in cfg:
        assert cfg["network"] in cfg["weights"] and (WEIGHTS / cfg["weights"]).is_file()
        assert cfg.get("lens", "") in cfg["weights"]
    for doc in cfg.get("docs", []):
        assert (ROOT / doc).is_file(), doc
    steps = reproduce.steps(cfg, tmp_path, seed=cfg["seed"])
    assert steps and all(s.argv[1:3] in (("-m", "blender_addon.factory"), ("-m", "dcdi_core"), ("-m", "lab"))
                          for s in steps)
    if "weights" in cfg:               # the last step writes the shipped file's name
        assert str(tmp_path / "weights" / cfg["weights"]) in steps[-1].argv


def test_a_folder_means_one_thing_across_the_configs():
    """Configs that share an OUT share a folder only if they make it alike."""
    seen = {}
    for name in reproduce.config_names():
        cfg = reproduce.load_config(name)
        for f in cfg.get("frames", []):
            spec = json.dumps({k: v for k, v in f.items() if k != "folder"}, sort_keys=True)
            assert seen.setdefault(f["folder"], spec) == spec, (name, f["folder"])


def test_the_seed_is_the_trained_and_exported_one(tmp_path):
    cfg = reproduce.load_config("dacn-mos-s1")
    lines = [s.line() for s in reproduce.steps(cfg, tmp_path, seed=3)]
    assert "--seeds 3,1" in lines[-2]
    assert lines[-1].endswith(f"refine-s3 --weights ema -o {tmp_path}/weights/dacn-mos-s1.npz")
    depth = [s.line() for s in reproduce.steps(reproduce.load_config("depth-mos-s2"), tmp_path)]
    assert "--seed 0 -o" in depth[-2] and "--lens-pool 8 --seed 0 --perturb 0.1 --no-refocus" in depth[3]
    olf = reproduce.steps(reproduce.load_config("olf-radial"), tmp_path, seed=0)
    assert len(olf) == 1 and olf[0].line().count("--lens ") == 4 and "--dtype float16 --seed 0 -o" in olf[0].line()


def test_the_scripts_flags_are_the_configs(tmp_path):
    """What the former reproduce_*.sh ran: the seeds, options and budgets of the shipped files."""
    lines = "\n".join(s.line() for n in reproduce.config_names()
                      for s in reproduce.steps(reproduce.load_config(n), tmp_path))
    for needed in ("--recipe leaves --count 200", "--perturb 0 --seed 7", "--lens-pool 4 --variants 2",
                   "--runs refine,refine@2m --seeds 0,1 --iters 9600 --lr 0.0005 --jobs 2",
                   "--runs baseline,da2t,refine,refine+mech,refine@2m --seeds 0,1 --iters 4800",
                   "--baseline-depth inf", "--full-sensor --placement centre --no-deconvolved",
                   "--iters 1500 --seed 0", "--seeds 0 1 --iters 1500", "--recipe leaves --count 72",
                   "--focus-lens double-gauss --focus-lens 6p --size tiny --iters 10000"):
        assert needed in lines, needed


def test_dry_run_prints_the_steps_and_runs_nothing(tmp_path, capsys):
    out = tmp_path / "out"
    assert reproduce.main(["dfd-refine-mos-s1", "--out", str(out), "--dry-run"]) == 0
    text = capsys.readouterr().out
    assert text.count(", todo]") == 21 and "dfd-refine-study" in text and "--export" in text
    assert not out.exists()


def test_a_finished_step_is_skipped(tmp_path, capsys, monkeypatch):
    cfg = reproduce.load_config("olf-radial")
    out = tmp_path / "out"
    ran = []
    monkeypatch.setattr(reproduce.subprocess, "call", lambda argv, cwd: ran.append(argv) or 0)
    assert reproduce.run(cfg, out) == 0 and len(ran) == 1
    assert reproduce.run(cfg, out) == 0 and len(ran) == 1          # done: recorded in OUT/reproduce.jsonl
    assert reproduce.run(cfg, out, seed=1) == 0 and len(ran) == 2  # another seed is another step
    monkeypatch.setattr(reproduce.subprocess, "call", lambda argv, cwd: 3)
    assert reproduce.run(reproduce.load_config("depth-mos-s1"), out) == 3


def test_a_bad_config_is_refused_by_name(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('seed = 0\n[[train]]\nkind = "magic"\n')
    assert reproduce.main([str(bad), "--out", str(tmp_path / "o"), "--dry-run"]) == 2
    assert "magic" in capsys.readouterr().err
    assert reproduce.main(["no-such-network", "--out", str(tmp_path / "o")]) == 2


@pytest.mark.parametrize("content, words", [(b"seed = 1\n\xff\xfe name = 'x'\n", "not UTF-8"),
                                             (b"seed = = 1\n", "not TOML"),
                                             (b"x = " + b"[" * 100_000 + b"]" * 100_000 + b"\n", "")])
def test_a_config_that_is_not_toml_is_one_line(tmp_path, content, words):
    f = tmp_path / "bad.toml"
    f.write_bytes(content)
    r = subprocess.run([sys.executable, "-m", "lab", "reproduce", str(f), "--out", str(tmp_path / "o"), "--dry-run"],
                       cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 2 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "bad.toml" in r.stderr and words in r.stderr


def test_a_damaged_resume_file_runs_the_steps_again(tmp_path):
    """The resume record with bytes that are not UTF-8, a line nested
    100,000 deep and a line that is not a record: read, never a traceback;
    the one good line counts as done."""
    log = tmp_path / "reproduce.jsonl"
    log.write_bytes(b'{"config": "x", "step": "a b"}\n\xff\xfe\n' + b"[" * 100_000 + b"]" * 100_000
                    + b'\n{"step": 5}\n[1, 2]\n')
    assert reproduce.finished(tmp_path) == {"a b"}
