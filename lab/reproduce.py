"""The shipped networks from scratch, each from its config (``lab/configs/NAME.toml``):

    python -m lab reproduce NAME --out OUT [--seed S] [--dry-run]
    python -m lab reproduce --list

A config is data: the textures it makes (``[[textures]]``: folder, count,
seed; ``dcdi dataset textures``), the factory frames it renders
(``[[frames]]``: folder, scene recipe, count, seed, the factory's lens, a
textures folder), the DA2T pairs made of them
(``[[pairs]]``: folder, frame folders, lens, ``dcdi dacn pairs`` options),
the training (``[[train]]``: a study of the lab or a ``dcdi`` trainer, its
options) and the export (``[export]``) that writes OUT/weights/<weights>,
the file shipped in ``dcdi_core/models/weights/``. Its ``seed`` is the
shipped file's training seed; ``--seed`` trains another (a study's other
seeds, ``extra_seeds``, run beside it for its table). Options are written as
the commands' long options: ``{iters = 9600}`` is ``--iters 9600``, ``true``
a flag, a list the option repeated.

Every step is one process run from the repository's root; OUT/reproduce.jsonl
records the steps that finished (by their command line), so the same
command again skips them and resumes the one that was stopped (the factory,
the pairs and every trainer resume a killed run themselves). ``--dry-run``
prints the steps, marking the finished ones, and runs nothing.
"""
from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = Path(__file__).resolve().parent / "configs"
WEIGHTS = ROOT / "dcdi_core" / "models" / "weights"
TRAIN_KINDS = ("dacn-study", "depth", "dfd-refine-study", "olf")
EXPORT_KINDS = ("dacn", "depth")
FACTORY_LENS = "mos-s1"          # the lens the factory simulates its frames through (the pairs make their own)


class ConfigError(ValueError):
    """A config that cannot be run: which file, which key, what is allowed."""


@dataclass(frozen=True)
class Step:
    what: str                    # frames, pairs, train, export
    argv: tuple

    def line(self) -> str:
        return shlex.join(self.argv)


MAX_CONFIG_BYTES = 1 << 20       # a config is a page of TOML


def config_names() -> list[str]:
    return sorted(p.stem for p in CONFIGS.glob("*.toml"))


def load_config(name: str) -> dict:
    """The config ``name`` (a name in lab/configs/ or a .toml path), checked for its keys' kinds."""
    path = Path(name) if name.endswith(".toml") else CONFIGS / f"{name}.toml"
    if not path.is_file():
        raise ConfigError(f"no config {name!r}: one of {', '.join(config_names())} (lab/configs/), or a .toml file")
    if path.stat().st_size > MAX_CONFIG_BYTES:
        raise ConfigError(f"{path}: {path.stat().st_size} bytes; a config is at most {MAX_CONFIG_BYTES}")
    try:
        cfg = tomllib.loads(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not TOML ({' '.join(str(e).split())})") from None
    except RecursionError:
        raise ConfigError(f"{path}: nested too deep to be a config") from None
    cfg.setdefault("name", path.stem)
    _check(cfg, path)
    return cfg


def _need(cond: bool, path: Path, what: str) -> None:
    if not cond:
        raise ConfigError(f"{path}: {what}")


def _check(cfg: dict, path: Path) -> None:
    _need(isinstance(cfg.get("seed"), int), path, "'seed' (the shipped file's training seed) must be an integer")
    _need(cfg.get("train"), path, "no [[train]] step")
    for x in cfg.get("textures", []):
        _need({"folder", "count", "seed"} <= set(x), path, f"[[textures]] {x}: folder, count, seed")
    for f in cfg.get("frames", []):
        _need({"folder", "recipe", "count", "seed"} <= set(f), path, f"[[frames]] {f}: folder, recipe, count, seed")
    for p in cfg.get("pairs", []):
        _need({"folder", "frames", "lens"} <= set(p) and isinstance(p["frames"], list), path,
              f"[[pairs]] {p}: folder, frames (a list of frame folders), lens")
    for t in cfg["train"]:
        _need(t.get("kind") in TRAIN_KINDS, path, f"[[train]] kind {t.get('kind')!r}: one of {', '.join(TRAIN_KINDS)}")
    if "weights" in cfg:
        exported = "export" in cfg or any(t.get("export") or t["kind"] == "olf" for t in cfg["train"])
        _need(exported, path, "'weights' names a file, but no step exports it ([export], or export = true)")
    if "export" in cfg:
        _need(cfg["export"].get("kind") in EXPORT_KINDS and "run" in cfg["export"] and "weights" in cfg, path,
              f"[export]: kind ({', '.join(EXPORT_KINDS)}), run, and a top-level 'weights'")


def options(table: dict | None) -> list[str]:
    """``{key = value}`` as long options: true a flag, false nothing, a list the option repeated."""
    out = []
    for key, value in (table or {}).items():
        flag = f"--{key}"
        if value is True:
            out.append(flag)
        elif value is False or value is None:
            continue
        elif isinstance(value, list):
            for v in value:
                out += [flag, str(v)]
        else:
            out += [flag, str(value)]
    return out


def seeds_of(step: dict, seed: int) -> list[int]:
    """The seed trained and exported first, then the study's other seeds (for its table)."""
    return [seed] + [s for s in step.get("extra_seeds", []) if s != seed]


def _study_export(export, weights, out: Path) -> tuple:
    """A study's --export: true, the config's shipped name; a file name, OUT/weights/<name> (an
    experiment's weights, shipped nowhere); absent, none."""
    if isinstance(export, str):
        return ("--export", str(out / "weights" / export))
    return ("--export", weights) if export else ()


def steps(cfg: dict, out: Path, seed: int | None = None, python: str = sys.executable) -> list[Step]:
    """The config's steps, in order, as command lines (run from the repository's root)."""
    seed = cfg["seed"] if seed is None else seed
    o = lambda folder: str(out / folder)  # noqa: E731
    dcdi, lab = [python, "-m", "dcdi_core"], [python, "-m", "lab"]
    out_steps = []
    for x in cfg.get("textures", []):
        out_steps.append(Step("textures", (*dcdi, "dataset", "textures", "-o", o(x["folder"]), "--count",
                                           str(x["count"]), "--seed", str(x["seed"]))))
    for f in cfg.get("frames", []):
        textures = ("--textures", o(f["textures"])) if "textures" in f else ()
        out_steps.append(Step("frames", (python, "-m", "blender_addon.factory", "--recipe", f["recipe"], "--count",
                                         str(f["count"]), "--lens", f.get("lens", FACTORY_LENS), "--out",
                                         o(f["folder"]), "--seed", str(f["seed"]), *textures,
                                         *options(f.get("options")))))
    for p in cfg.get("pairs", []):
        for frames in p["frames"]:
            out_steps.append(Step("pairs", (*dcdi, "dacn", "pairs", o(frames), "--lens", p["lens"], "-o",
                                            o(p["folder"]), *options(p.get("options")))))
    weights = str(out / "weights" / cfg["weights"]) if "weights" in cfg else None
    for t in cfg["train"]:
        kind, opts = t["kind"], options(t.get("options"))
        seeds = seeds_of(t, seed)
        if kind == "dacn-study":
            argv = (*lab, "dacn-study", o(t["folder"]), "--lens", t["lens"], "--train", o(t["train"]), "--test",
                    o(t["test"]), "--runs", ",".join(t["runs"]), "--seeds", ",".join(map(str, seeds)), *opts)
        elif kind == "dfd-refine-study":
            argv = (*lab, "dfd-refine-study", "--lens", t["lens"], "--train", *map(o, t["train"]), "--val",
                    *map(o, t["val"]), "--test", *map(o, t["test"]), "--seeds", *map(str, seeds), *opts,
                    "--out", o(t["folder"])) + _study_export(t.get("export"), weights, out)
        elif kind == "depth":
            argv = (*dcdi, "depth", "train", "--data", o(t["data"]), *opts, "--seed", str(seed), "-o", o(t["folder"]))
        else:                                           # olf: trains and exports in one command
            lenses = [x for lens in t["lens"] for x in ("--lens", lens)]
            argv = (*dcdi, "olf", "train", *lenses, *opts, "--seed", str(seed), "-o", weights)
        out_steps.append(Step("train", argv))
    if "export" in cfg:
        e = cfg["export"]
        out_steps.append(Step("export", (*dcdi, e["kind"], "export", o(e["run"].format(seed=seed)),
                                         *options(e.get("options")), "-o", weights)))
    return out_steps


def _done_log(out: Path) -> Path:
    return out / "reproduce.jsonl"


def finished(out: Path) -> set[str]:
    log = _done_log(out)
    if not log.is_file():
        return set()
    from dcdi_core.errors import DcdiError
    from dcdi_core.io.jsontext import loads
    done = set()
    # a byte that is not UTF-8, a line nested deep, a line that is not ours: that step is not done (it runs again)
    for n, line in enumerate(log.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
        try:
            step = loads(line, f"{log} line {n}")["step"]
        except (DcdiError, KeyError, TypeError):
            continue                                    # a torn last line: that step runs again
        if isinstance(step, str):
            done.add(step)
    return done


def run(cfg: dict, out: Path, seed: int | None = None, dry_run: bool = False, log=print) -> int:
    out = out.resolve()
    todo = steps(cfg, out, seed)
    done = finished(out)
    log(f"reproduce {cfg['name']}: {cfg.get('about', '')}; {len(todo)} steps into {out}"
        + (f", then OUT/weights/{cfg['weights']}" if "weights" in cfg else ""))
    for i, s in enumerate(todo, 1):
        mark = "done" if s.line() in done else "todo"
        if dry_run or mark == "done":
            log(f"  [{i}/{len(todo)} {s.what}, {mark}] {s.line()}")
            continue
        log(f"  [{i}/{len(todo)} {s.what}] {s.line()}")
        out.mkdir(parents=True, exist_ok=True)
        code = subprocess.call(list(s.argv), cwd=ROOT)       # `-m` finds lab/, blender_addon/ there
        if code != 0:
            log(f"reproduce {cfg['name']}: step {i} failed (exit {code}); the same command again resumes it")
            return code
        with open(_done_log(out), "a", encoding="utf-8") as f:
            f.write(json.dumps({"config": cfg["name"], "step": s.line()}) + "\n")
    if not dry_run and "weights" in cfg:
        log(f"reproduce {cfg['name']}: done: {out / 'weights' / cfg['weights']} (the shipped one: "
            f"{WEIGHTS.relative_to(ROOT) / cfg['weights']})")
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m lab reproduce", description=__doc__.split("\n\n")[0])
    p.add_argument("name", nargs="?", help=f"a config: {', '.join(config_names())} (or a .toml file)")
    p.add_argument("--out", type=Path, help="folder for the frames, pairs, runs and OUT/weights/")
    p.add_argument("--seed", type=int, default=None, help="the training seed (default: the shipped file's)")
    p.add_argument("--dry-run", action="store_true", help="print the steps (finished ones marked), run nothing")
    p.add_argument("--list", action="store_true", help="list the configs and what each makes")
    a = p.parse_args(argv)
    if a.list:
        for n in config_names():
            cfg = load_config(n)
            print(f"{n}: {cfg.get('about', '')}" + (f" -> {cfg['weights']}" if "weights" in cfg else ""))
        return 0
    if a.name is None or a.out is None:
        p.error("give a config NAME and --out OUT (or --list)")
    try:
        cfg = load_config(a.name)
    except ConfigError as e:
        print(f"lab reproduce: error: {e}", file=sys.stderr)
        return 2
    return run(cfg, a.out, a.seed, a.dry_run)


if __name__ == "__main__":
    sys.exit(main())
