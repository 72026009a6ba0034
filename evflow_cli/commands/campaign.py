"""Campaigns: long training kept resumable in the repository (evflow_cli/campaign.py says what the
folder holds).

  python scripts/campaign.py new mgr-devval --export ev-mgrflownet-cpu-next \\
      --init ev-mgrflownet-cpu-synthetic --val-data '../shared/devval/*.h5' -- <scripts/train.py options>
  python scripts/campaign.py resume mgr-devval --hours 2.5 --background   # on any machine, any clone
  python scripts/campaign.py status mgr-devval
  python scripts/campaign.py stop mgr-devval                              # SIGTERM: saves, then stops
  python scripts/campaign.py plot mgr-devval
  python scripts/campaign.py anneal mgr-devval --steps 3000            # a new campaign: its export, annealed

resume trains in stretches of the campaign's interval (train.py --resume in runs/campaigns/NAME/),
and after each: validates (evaluate.py on the validation data, every window unless the campaign
says otherwise; score = mean over dt of the model's AEE / the reference row's AEE, the network run
one pass per window or, with val_split "dt", as the shipped default runs it), appends the
curve, exports the weights as float16 + provenance to agents/weights/EXPORT when the score is the
campaign's best, and writes the slim resume state agents/campaigns/NAME/state.pt. SIGTERM or
SIGINT stop the training step in progress, save, write the state and exit 0. On a fresh clone
the state is where it continues from; nothing here writes to git (tools/campaign_commit.py does).
"""

from __future__ import annotations

import argparse
import datetime
import glob
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from agents.options import (
    DeviceOptions,
    check_choices,
    command_parser,
    non_negative_int,
    option,
    options_from_args,
    positive_float,
    positive_int,
)
from envs.outputs import folder_holder, hold_folder, release_folder
from evflow_cli.campaign import STATE_BUDGET, Campaign, CampaignSpec, machine, plot_curve, read_json, write_json

ROOT = Path(__file__).resolve().parents[2]  # the checkout
PYTHON = sys.executable


def _expand(patterns: list[str]) -> list[str]:
    """Validation data: split names stay, file patterns are expanded (relative to the checkout)."""
    out = []
    for pattern in patterns:
        if any(ch in pattern for ch in "*?[") or pattern.endswith(".h5") or "/" in pattern:
            base = pattern if os.path.isabs(pattern) else str(ROOT / pattern)
            found = sorted(glob.glob(base))
            if not found:
                raise FileNotFoundError(f"validation data {pattern!r}: no file matches (looked in {Path(base).parent})")
            out += found
        else:
            out.append(pattern)
    return out


def _evaluate(args: list[str], out: Path, device: str, env: dict | None = None) -> dict:
    """evaluate.py in a child process (``env``: its environment, e.g. the campaign's thread count)."""
    if out.exists():  # the campaign's own folder of an earlier try of this validation: replaced
        shutil.rmtree(out)
    out.mkdir(parents=True)
    cmd = [PYTHON, str(ROOT / "scripts" / "evaluate.py"), *args, "--pictures", "0", "--no-progress",
           "--out", str(out), "--device", device]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, env=env)
    return read_json(out / "results.json", "evaluation result")


def _eval_data_args(spec: CampaignSpec) -> list[str]:
    return ["--data", *_expand(spec.val_data), "--window-size", *map(str, spec.val_dt),
            *(["--max-windows", str(spec.val_windows)] if spec.val_windows else [])]


def _aee(block: dict, dts: list[int]) -> dict[str, float]:
    return {f"dt{d}": block["overall"][f"dt{d}"]["aee"] for d in dts}


def reference(campaign: Campaign, spec: CampaignSpec, device: str, log, env: dict | None = None) -> dict:
    """The reference row's AEE per dt on the validation data (computed once, then read)."""
    key = {"data": spec.val_data, "dt": spec.val_dt, "windows": spec.val_windows, "reference": spec.reference}
    if campaign.reference_path.exists():
        try:
            stored = read_json(campaign.reference_path, "reference row")
        except ValueError as err:  # derived data: computed again rather than trusted or fatal
            log(f"[campaign] {err}; computing it again")
            stored = {}
        if isinstance(stored, dict) and {k: stored.get(k) for k in key} == key:
            return stored
    log(f"[campaign] computing the reference row ({spec.reference}) on the validation data, once")
    start = time.time()
    flag = "--cmax" if spec.reference == "cmax" else "--zero"
    results = _evaluate([flag, *_eval_data_args(spec)], campaign.work / "val" / "reference", device, env)
    block = results if results["method"] != "model" else results["baselines"][spec.reference]
    sequences = {name: {k: v.get("aee") for k, v in seq.items() if k.startswith("dt")}
                 for name, seq in block["sequences"].items()}
    stored = {**key, "aee": _aee(block, spec.val_dt), "sequences": sequences, "seconds": round(time.time() - start),
              "date": datetime.date.today().isoformat()}
    write_json(campaign.reference_path, stored)
    return stored


def validate(campaign: Campaign, spec: CampaignSpec, weights: list[str], tag: str, device: str, log,
             env: dict | None = None) -> dict:
    """Score the weights (``--checkpoint PATH`` or ``--pretrained NAME``) on the validation data."""
    ref = reference(campaign, spec, device, log, env)
    if spec.val_split == "finish":
        split, marker = ["--finish"], " + finish "
    else:
        split, marker = (["--split", spec.val_split], f" + split {spec.val_split}") if spec.val_split else ([], "")
    results = _evaluate([*weights, "--name", "model", *split, *_eval_data_args(spec)], campaign.work / "val" / tag,
                        device, env)
    block = results  # the first row: the weights one pass per window (named "model", or "NAME (pretrained)")
    if spec.val_split:
        block = next((row for name, row in results["baselines"].items()
                      if name.endswith(marker) or (marker == " + finish " and marker in name)), None)
        if block is None:
            raise RuntimeError(f"campaign {spec.name}: the validation run has no '{marker.strip()}' row "
                               f"(rows: {', '.join(results['baselines'])})")
    aee = _aee(block, spec.val_dt)
    score = sum(aee[k] / ref["aee"][k] for k in aee) / len(aee)
    sequences = {name: {k: v.get("aee") for k, v in seq.items() if k.startswith("dt")}
                 for name, seq in block["sequences"].items()}
    row = {"score": round(score, 5), "aee": aee, "reference_aee": ref["aee"], "sequences": sequences}
    if spec.val_split:  # the one pass beside it, from the same run
        row.update(mode=spec.mode, aee_one_pass=_aee(results, spec.val_dt))
    return row


def rescore_export(campaign: Campaign, spec: CampaignSpec, weights_dir: Path, here: str, progress: dict,
                   device: str, log, env: dict | None = None) -> None:
    """When the campaign's score changed mode, its current export is scored in the new mode first,
    so that a later step is exported only when it beats the export in the same terms."""
    mode = spec.mode
    rows = campaign.curve()
    if not rows or any(r.get("mode") == mode for r in rows) or not (weights_dir / f"{spec.export}.pt").exists():
        return
    meta = weights_dir / f"{spec.export}.json"
    step = read_json(meta, "weights' provenance").get("validation", {}).get("step") if meta.exists() else None
    row = validate(campaign, spec, ["--checkpoint", str(weights_dir / f"{spec.export}.pt")], "export", device, log,
                   env)
    campaign.append_curve({"step": step, **row, "wall_h": round(progress.get("wall_s", 0.0) / 3600, 4),
                           "stretch": progress["stretches"], "machine": here,
                           "date": datetime.date.today().isoformat(), "exported": False,
                           "rescored": f"the export ({spec.export}, step {step}) in the campaign's new mode"})
    log(f"[campaign] the score's mode is now {mode or 'one pass'}: the export (step {step}) scores "
        f"{row['score']:.4f} {row['aee']} in it")


def _steps_of(recipe: list[str]) -> list[str]:
    """``--steps N`` of a recipe (a campaign's budget may grow between stretches), or nothing."""
    for i, arg in enumerate(recipe):
        if arg == "--steps" and i + 1 < len(recipe):
            return ["--steps", recipe[i + 1]]
        if arg.startswith("--steps="):
            return ["--steps", arg.split("=", 1)[1]]
    return []


def _drop_option(recipe: list[str], flag: str) -> list[str]:
    """``recipe`` without the single-valued option ``flag`` (in either spelling)."""
    out, i = [], 0
    while i < len(recipe):
        arg = recipe[i]
        if arg == flag:
            i += 2  # the flag and its value
            continue
        if not arg.startswith(f"{flag}="):
            out.append(arg)
        i += 1
    return out


def _set_option(recipe: list[str], flag: str, value: str) -> list[str]:
    """``recipe`` with the single-valued option ``flag`` set to ``value`` (replaced where present,
    in either spelling, else appended)."""
    return [*_drop_option(recipe, flag), flag, value]


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _die_with_parent() -> None:
    """In a campaign's child, before it runs: the kernel sends it SIGTERM (train.py saves and stops)
    when the campaign dies, even by SIGKILL, so no trainer outlives its campaign (Linux; elsewhere
    a no-op)."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def cmd_new(args, rest: list[str]) -> int:
    campaign = Campaign(args.name, args.campaigns_dir)
    if campaign.spec_path.exists() and not args.force:
        raise SystemExit(f"campaign {args.name!r} exists ({campaign.spec_path}); --force replaces its description "
                         "(not its state)")
    banned = sorted({a for a in rest if a.split("=")[0] in ("--out", "--resume", "--init", "--minutes")})
    if banned:
        raise SystemExit(f"the recipe (after --) must not set {', '.join(banned)}: the campaign sets them")
    from evflow_cli.commands.train import parse_args

    # a recipe train.py would refuse fails here, as the first stretch runs it (with the campaign's --init)
    parse_args([*rest, "--out", str(campaign.work / "train"), *(["--init", args.init] if args.init else [])])
    spec = CampaignSpec(name=args.name, export=args.export, train=rest, init=args.init, val_data=args.val_data,
                        val_dt=args.val_window_size, val_windows=args.val_windows, val_split=args.val_split,
                        reference=args.reference,
                        interval_minutes=args.interval_minutes, state_budget_mb=args.state_budget_mb, note=args.note)
    spec.write(campaign.spec_path)
    print(f"wrote {campaign.spec_path}; start it with: python scripts/campaign.py resume {args.name} --background")
    return 0


def cmd_anneal(args) -> int:
    """A new campaign that continues NAME's recipe from NAME's export with the step size warmed up
    and then annealed to zero over a fixed budget (docs/training.md, "End a campaign by annealing")."""
    source = Campaign(args.name, args.campaigns_dir, args.runs)
    spec = source.spec()
    into = args.into or f"{args.name}-cooldown"
    if into == args.name:
        raise SystemExit(f"--into {into!r}: the annealed campaign needs a name of its own")
    target = Campaign(into, args.campaigns_dir)
    if target.spec_path.exists() and not args.force:
        raise SystemExit(f"campaign {into!r} exists ({target.spec_path}); --force replaces its description "
                         "(not its state)")
    if folder_holder(source.work) is not None:
        raise SystemExit(f"campaign {args.name!r} is running here: its export may still change; stop it first "
                         f"(python scripts/campaign.py stop {args.name})")
    if args.warmup_steps >= args.steps:
        raise SystemExit(f"--warmup-steps {args.warmup_steps} must be fewer than --steps {args.steps}")
    weights_dir = Path(args.weights_dir) if args.weights_dir else ROOT / "agents" / "weights"
    if args.init:
        init, origin = args.init, f"from {args.init}"
    else:
        exported = weights_dir / f"{spec.export}.pt"
        if not exported.exists():
            raise SystemExit(f"campaign {args.name!r} has no export yet ({exported}): let a validation export it, "
                             "or give the weights to anneal with --init")
        record = weights_dir / f"{spec.export}.json"
        validation = read_json(record, "weights' provenance").get("validation", {}) if record.exists() else {}
        init = spec.export if weights_dir.resolve() == (ROOT / "agents" / "weights").resolve() else str(exported.resolve())
        origin = (f"from its export {spec.export} (step {validation.get('step', '?')}, validation score "
                  f"{validation.get('score', '?')}, {validation.get('mode', 'one pass')})" if validation
                  else f"from its export {spec.export}")
    # --revive acts once, on the weights a campaign starts from: the annealed one starts from revived weights
    recipe = _set_option(_drop_option(spec.train, "--revive"), "--steps", str(args.steps))
    recipe = _set_option(recipe, "--warmup-steps", str(args.warmup_steps))
    recipe = _set_option(recipe, "--decay", "cosine")
    if args.lr is not None:
        recipe = _set_option(recipe, "--lr", str(args.lr))
    from evflow_cli.commands.train import parse_args

    parsed = parse_args([*recipe, "--out", str(target.work / "train"), "--init", init])  # as its first stretch runs it
    note = (f"campaign {args.name}'s recipe annealed {origin}: {args.steps} steps, {args.warmup_steps} of warm-up "
            f"to {parsed.lr:g}, then a cosine decay of the step size to zero")
    annealed = CampaignSpec(**{**vars(spec), "name": into, "export": args.export or f"{spec.export}-cooldown",
                               "train": recipe, "init": init, "note": note})
    annealed.write(target.spec_path)
    if source.reference_path.exists() and not target.reference_path.exists():  # same validation: same reference
        shutil.copyfile(source.reference_path, target.reference_path)
    print(f"wrote {target.spec_path} ({note}); start it with: python scripts/campaign.py resume {into} --background")
    return 0


def cmd_resume(args) -> int:
    campaign = Campaign(args.name, args.campaigns_dir, args.runs)
    spec = campaign.spec()
    campaign.work.mkdir(parents=True, exist_ok=True)
    holder = folder_holder(campaign.work)
    if holder is not None and holder != os.getpid():
        raise SystemExit(f"campaign {args.name!r} is already running (pid {holder}); stop it with "
                         f"scripts/campaign.py stop {args.name}")
    if args.background:
        log = campaign.work / "campaign.log"
        argv = [a for a in sys.argv[1:] if a != "--background"]
        argv += [] if "--quiet" in argv else ["--quiet"]
        with open(log, "a") as f:
            child = subprocess.Popen([PYTHON, str(ROOT / "scripts" / "campaign.py"), *argv], stdout=f,
                                     stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True,
                                     cwd=os.getcwd())
        print(f"campaign {args.name} resumed in the background (pid {child.pid}); progress: {log}; "
              f"stop it with: python scripts/campaign.py stop {args.name}")
        return 0
    try:  # the campaign's one runner for the life of this process: the kernel releases it however it ends
        hold_folder(campaign.work, f"campaign {args.name}:")
    except FileExistsError as err:
        raise SystemExit(str(err)) from None
    try:
        return _resume(campaign, spec, args)
    finally:
        release_folder(campaign.work)


def _child_env(threads: int | None) -> dict[str, str]:
    """The environment of the children: training and validation run with the campaign's --threads."""
    env = dict(os.environ)
    if threads:
        env.update({k: str(threads) for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")})
    return env


def _validate_init(campaign: Campaign, spec: CampaignSpec, here: str, device: str, log, env: dict) -> None:
    """Score the initial weights (``spec.init``: a shipped name or a checkpoint) as the curve's step 0."""
    row = validate(campaign, spec, ["--pretrained", spec.init] if "/" not in spec.init and not spec.init.endswith(
        ".pt") else ["--checkpoint", spec.init], "init", device, log, env)
    campaign.append_curve({"step": 0, **row, "wall_h": 0.0, "stretch": 0, "machine": here, "init": spec.init,
                           "date": datetime.date.today().isoformat()})
    log(f"[campaign] the initial weights ({spec.init}): score {row['score']:.4f} {row['aee']}")


def _train_args(campaign: Campaign, spec: CampaignSpec, args, minutes: float) -> list[str]:
    """train.py's arguments for one interval of ``minutes``: resuming the working checkpoint
    where there is one, else the recipe from its start (and ``spec.init``)."""
    train = ["--out", str(campaign.work / "train"), "--minutes", f"{minutes:.2f}", "--val-data", "",
             "--device", args.device, *(["--no-progress"] if args.quiet else [])]
    if campaign.checkpoint.exists():  # the recipe's step count may have grown since
        return ["--resume", *train, *_steps_of(spec.train)]
    return [*spec.train, *train, *(["--init", spec.init] if spec.init else [])]


def _validate_step(campaign: Campaign, spec: CampaignSpec, step: int, progress: dict, here: str, weights_dir: Path,
                   device: str, log, env: dict) -> None:
    """Score the working checkpoint at ``step``, add it to the curve, and export it when it
    beats the best so far."""
    row = validate(campaign, spec, ["--checkpoint", str(campaign.checkpoint)], f"step{step}", device,
                   log, env)
    best = campaign.best(spec.mode)
    improved = best is None or row["score"] < best["score"]
    campaign.append_curve({"step": step, **row, "wall_h": round(progress["wall_s"] / 3600, 4),
                           "stretch": progress["stretches"], "machine": here,
                           "date": datetime.date.today().isoformat(), "exported": improved})
    log(f"[campaign] step {step}: score {row['score']:.4f} {row['aee']} "
        f"(best before: {best['score'] if best else '-'})")
    if improved:
        name, users = export(campaign, spec, row, step, here, weights_dir)
        kept = f" ({spec.export} is the init of {', '.join(users)}: left as it is)" if users else ""
        log(f"[campaign] exported to {weights_dir / name}.pt{kept}")


def _resume(campaign: Campaign, spec: CampaignSpec, args) -> int:
    def log(message: str) -> None:
        print(f"{datetime.datetime.now():%H:%M:%S} {message}", flush=True)

    stop = {"signal": None}
    child: dict = {"proc": None}

    def on_signal(signum, _frame):
        stop["signal"] = signum
        if child["proc"] is not None and child["proc"].poll() is None:
            child["proc"].send_signal(signal.SIGTERM)  # train.py finishes its step and saves

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
    env = _child_env(args.threads)
    weights_dir = Path(args.weights_dir) if args.weights_dir else ROOT / "agents" / "weights"
    source = campaign.restore_working_checkpoint()
    progress = campaign.progress()
    progress["stretches"] = int(progress.get("stretches", 0)) + 1
    here = machine(args.device)
    log(f"[campaign] {campaign.name}: stretch {progress['stretches']} on {here}, from the "
        f"{ {'working': 'working checkpoint', 'state': 'committed state', 'fresh': 'start'}[source]}")
    if source == "fresh" and spec.init and spec.val_data and not campaign.curve():
        _validate_init(campaign, spec, here, args.device, log, env)
    elif spec.val_data:
        rescore_export(campaign, spec, weights_dir, here, progress, args.device, log, env)
    deadline = time.time() + 3600 * args.hours if args.hours else float("inf")
    if args.minutes:
        deadline = min(deadline, time.time() + 60 * args.minutes)
    try:
        while time.time() < deadline and stop["signal"] is None:
            minutes = min(spec.interval_minutes, max(0.25, (deadline - time.time()) / 60))
            train = _train_args(campaign, spec, args, minutes)
            started = time.time()
            child["proc"] = subprocess.Popen([PYTHON, str(ROOT / "scripts" / "train.py"), *train], env=env,
                                             preexec_fn=_die_with_parent)
            code = child["proc"].wait()
            child["proc"] = None
            progress["wall_s"] = float(progress.get("wall_s", 0.0)) + time.time() - started
            if code != 0:
                raise SystemExit(f"[campaign] train.py exited with {code}; the state keeps the last good interval")
            from agents.checkpoint import load_checkpoint

            payload = load_checkpoint(campaign.checkpoint)
            step, total = int(payload["step"]), int(payload["config"]["steps"])
            if stop["signal"] is None and spec.val_data:
                _validate_step(campaign, spec, step, progress, here, weights_dir, args.device, log, env)
            size, dropped = campaign.write_state(campaign.checkpoint, progress, int(spec.state_budget_mb * 2**20))
            log(f"[campaign] state at step {step}: {campaign.state_path} ({size / 2**20:.1f} MB; left out to fit "
                f"{spec.state_budget_mb:g} MB: {dropped})")
            if step >= total:
                log(f"[campaign] reached the recipe's {total} steps")
                break
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if campaign.curve():
        plot_curve(campaign.curve(), campaign.dir / "curve.png", f"campaign {campaign.name}")
    if stop["signal"] is not None:
        log(f"[campaign] {signal.Signals(stop['signal']).name}: stopped; state saved")
    return 0


def pinned_by(campaign: Campaign, model: str) -> list[str]:
    """The other campaigns beside ``campaign`` whose ``init`` is the shipped ``model``: replacing
    that file would change what their configurations reproduce."""
    users = []
    for path in sorted(campaign.dir.parent.glob("*/campaign.json")):
        if path.parent.name == campaign.name:
            continue
        try:
            init = json.loads(path.read_text()).get("init")
        except (OSError, ValueError):  # not a campaign this check can read: it names no init
            continue
        if init == model:
            users.append(path.parent.name)
    return users


def export(campaign: Campaign, spec: CampaignSpec, row: dict, step: int, here: str,
           weights_dir: Path) -> tuple[str, list[str]]:
    """Export the campaign's checkpoint as ``spec.export``, or as ``spec.export + "-latest"`` when
    another campaign starts from ``spec.export`` (:func:`pinned_by`). Returns (the name written,
    the campaigns that start from ``spec.export``)."""
    from agents.pretrained import export_pretrained

    users = pinned_by(campaign, spec.export)
    name = f"{spec.export}-latest" if users else spec.export

    provenance = {
        "command": f"python scripts/campaign.py resume {campaign.name} (agents/campaigns/{campaign.name}/campaign.json:"
                   f" train.py {' '.join(spec.train)}" + (f", from {spec.init}" if spec.init else "") + ")",
        "campaign": campaign.name,
        "date": datetime.date.today().isoformat(),
        "note": spec.note,
        "machine": here,
        "validation": {"data": spec.val_data, "dt": spec.val_dt, "windows_per_sequence": spec.val_windows or "all",
                       "score": row["score"], "aee": row["aee"], "reference_aee": row["reference_aee"],
                       "definition": f"mean over dt of AEE / the {spec.reference} row's AEE"
                                     + (f", the network run with {spec.mode}" if spec.val_split else ""),
                       "mode": spec.mode or "one pass", "step": step},
    }
    if users:
        provenance["note"] = (f"{spec.note} (exported as {name}: {spec.export} is the init of "
                              f"{', '.join(users)})").lstrip()
    export_pretrained(campaign.checkpoint, name, provenance, directory=weights_dir, overwrite=True)  # its own export
    return name, users


def _data_of(recipe: list[str]) -> list[str]:
    """The values of the recipe's ``--data`` (train.py's default split when absent)."""
    if "--data" not in recipe:
        return ["synthetic-train"]
    values = []
    for arg in recipe[recipe.index("--data") + 1 :]:
        if arg.startswith("--"):
            break
        values.append(arg)
    return values


def cmd_prepare(args) -> int:
    """Simulate the synthetic splits the recipe trains on into the disk cache, in parallel
    (a fresh machine; training would otherwise simulate them one by one on first use)."""
    from envs.synthetic import list_sequences

    spec = Campaign(args.name, args.campaigns_dir, args.runs).spec()
    for data in _data_of(spec.train):
        try:
            list_sequences(data)
        except (ValueError, KeyError):
            print(f"{data}: not a synthetic split, nothing to simulate")
            continue
        subprocess.run([PYTHON, str(ROOT / "scripts" / "generate_synthetic.py"), "--split", data, "--cache",
                        "--workers", str(args.workers)], check=True)
    return 0


def cmd_stop(args) -> int:
    campaign = Campaign(args.name, args.campaigns_dir, args.runs)
    pid = folder_holder(campaign.work)  # only the process holding the campaign's lock is signalled
    if pid is None or pid <= 0:
        print(f"campaign {args.name!r} is not running here (nobody holds {campaign.work / 'writer.lock'})")
        return 0
    os.kill(pid, signal.SIGTERM)
    deadline = time.time() + args.timeout
    while _pid_alive(pid) and time.time() < deadline:
        time.sleep(1)
    if _pid_alive(pid):
        raise SystemExit(f"campaign {args.name!r} (pid {pid}) still runs after {args.timeout} s")
    step = campaign.state_step()
    print(f"campaign {args.name!r} stopped; " + (f"state at step {step} in {campaign.state_path}" if step is not None
                                                 else f"no state written yet ({campaign.state_path} absent)"))
    return 0


def cmd_status(args) -> int:
    campaign = Campaign(args.name, args.campaigns_dir, args.runs)
    spec = campaign.spec()
    progress = campaign.progress()
    best = campaign.best(spec.mode)
    size = campaign.state_path.stat().st_size / 2**20 if campaign.state_path.exists() else 0.0
    running = folder_holder(campaign.work) is not None
    print(f"campaign {campaign.name}: exports {spec.export}; state step {campaign.state_step()} ({size:.1f} MB); "
          f"{progress.get('wall_s', 0) / 3600:.2f} training hours over {progress.get('stretches', 0)} stretches; "
          f"{'running here' if running else 'not running here'}")
    for row in campaign.curve():
        print(f"  step {row['step']!s:>7}  score {row['score']:.4f}  " + "  ".join(
            f"{k} {v:.3f}" for k, v in row["aee"].items()) + f"  {row.get('wall_h', 0):.2f} h  {row.get('machine', '')}"
            + f"  {row.get('mode') or 'one pass'}")
    if best:
        print(f"best: step {best['step']}, score {best['score']:.4f}")
    return 0


def cmd_plot(args) -> int:
    campaign = Campaign(args.name, args.campaigns_dir, args.runs)
    path = plot_curve(campaign.curve(), campaign.dir / "curve.png", f"campaign {campaign.name}")
    print(path or "matplotlib is missing: pip install -e '.[plots]'")
    return 0


@dataclass(kw_only=True)
class CampaignOptions:
    """The campaign a subcommand acts on (every subcommand takes these)."""

    name: str = option(positional=True)
    """the campaign (a folder of --campaigns-dir)"""
    campaigns_dir: Path | None = None
    """where campaigns live (default: agents/campaigns of this checkout)"""
    runs: Path = Path("runs") / "campaigns"
    """working folder of the runs"""


@dataclass(kw_only=True)
class NewOptions(CampaignOptions):
    """``new``: the campaign's description (train.py's options of its recipe follow ``--``)."""

    export: str = option(required=True)
    """shipped model name its improved weights are exported to"""
    init: str | None = None
    """weights the first stretch starts from (shipped name or checkpoint)"""
    val_data: list[str] = option(nargs="*", default_factory=lambda: ["../shared/devval/*.h5"])
    """validation data (split names or file patterns relative to the checkout; none: no validation)"""
    val_window_size: list[int] = option(default_factory=lambda: [1, 4], type=positive_int, aliases=("--val-dt",),
                                        metavar="N")
    """the validation's window lengths in ground-truth frames (evaluate.py --window-size): the score is the mean over them"""
    val_windows: int | None = option(None, type=positive_int)
    """windows per validation sequence (default: all)"""
    val_split: str | None = option(None, choices=("dt", "finish"))
    """score the network in a mode: 'finish', one pass per window finished by the default's short solve (evaluate.py --finish, the shipped default's mode); 'dt', one step per ground-truth interval (evaluate.py --split dt); default: one pass per window"""
    reference: Literal["cmax", "zero"] = "cmax"
    """the score's reference row"""
    interval_minutes: float = option(20.0, type=positive_float)
    """training between state writes"""
    state_budget_mb: float = option(STATE_BUDGET / 2**20, type=positive_float)
    """the most the committed resume state may weigh (Adam's moments are dropped to fit)"""
    note: str = ""
    """what the campaign is, for the provenance"""
    force: bool = False
    """replace an existing description"""

    def __post_init__(self) -> None:
        check_choices(self)


@dataclass(kw_only=True)
class ResumeOptions(CampaignOptions, DeviceOptions):
    """``resume``: how long this stretch trains, where (--threads: of the training process)."""

    hours: float | None = option(None, type=positive_float)
    """stop after this long (default: until its steps)"""
    minutes: float | None = option(None, type=positive_float)
    """stop after this many minutes"""
    weights_dir: str | None = None
    """where improved weights go (default agents/weights)"""
    background: bool = False
    """detach; progress in runs/campaigns/NAME/campaign.log"""
    quiet: bool = False
    """no per-step progress bar (the background's log)"""


@dataclass(kw_only=True)
class AnnealOptions(CampaignOptions):
    """``anneal``: the new campaign that ends NAME with a decaying step size."""

    into: str | None = None
    """the new campaign's name (default: NAME-cooldown)"""
    export: str | None = None
    """its shipped model name (default: NAME's export + -cooldown)"""
    init: str | None = None
    """the weights it starts from (default: NAME's export, its best validation so far)"""
    weights_dir: str | None = None
    """where NAME's export lies (default agents/weights)"""
    steps: int = option(3000, type=positive_int)
    """training steps of the annealing"""
    warmup_steps: int = option(50, type=non_negative_int)
    """steps of linear warm-up of the step size (train.py's: over the first steps of the cosine)"""
    lr: float | None = option(None, type=positive_float)
    """the peak step size (default: the recipe's)"""
    force: bool = False
    """replace an existing description"""


@dataclass(kw_only=True)
class StopOptions(CampaignOptions):
    """``stop``: how long to wait for the state to be written."""

    timeout: float = option(900.0, type=positive_float)
    """seconds to wait for the campaign to save and exit"""


@dataclass(kw_only=True)
class PrepareOptions(CampaignOptions):
    """``prepare``: how many processes simulate."""

    workers: int = option(os.cpu_count() or 1, type=positive_int)
    """simulate in this many processes"""


#: subcommand -> (its options, its one-line help)
SUBCOMMANDS = {
    "new": (NewOptions, "describe a campaign: NAME, options, then -- and train.py's options"),
    "resume": (ResumeOptions, "continue (or start) a campaign"),
    "stop": (StopOptions, "SIGTERM a running campaign and wait until its state is written"),
    "prepare": (PrepareOptions, "simulate the recipe's synthetic training data ahead, in parallel"),
    "status": (CampaignOptions, "step, training hours and the validation curve"),
    "plot": (CampaignOptions, "draw curve.png from curve.jsonl"),
    "anneal": (AnnealOptions, "describe a new campaign: NAME's recipe from its export, the step size annealed to zero"),
}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    for command, (cls, summary) in SUBCOMMANDS.items():
        command_parser(cls, parser=sub.add_parser(command, help=summary, description=summary))
    return p


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    cut = argv.index("--") if "--" in argv else len(argv)
    parsed = build_parser().parse_args(argv[:cut])
    command = parsed.command
    args = options_from_args(SUBCOMMANDS[command][0], parsed)
    if command != "new" and cut < len(argv):
        raise SystemExit("only 'new' takes train.py options after --")
    if command == "new":
        return cmd_new(args, argv[cut + 1 :])
    return {"resume": cmd_resume, "prepare": cmd_prepare, "stop": cmd_stop, "status": cmd_status, "plot": cmd_plot,
            "anneal": cmd_anneal}[command](args)


if __name__ == "__main__":
    sys.exit(main())
