"""Issue 20's acceptance matrix: bad inputs and faults against every ``unipixie`` command, each case a real
subprocess in its own temporary folder, each outcome classified automatically.

Run (about 10 minutes on 2 cores; ``--jobs 2`` and ``nice -n 10`` are the defaults)::

    PYTHONPATH=... python tests/fault_matrix/run_matrix.py --out benchmarks/fault_matrix.json
    python tests/fault_matrix/run_matrix.py --only bake.         # cases whose id starts with "bake."
    python tests/fault_matrix/run_matrix.py --list                # the cases, not run

A case is: a command line, the files it gets (copies of small fixtures made once, or crafted bad ones), the
exit statuses it may end with (README "Exit statuses": 0 done, 1 internal error, 2 bad input, 3 simulation
failed, 130 cancelled), its final output names, and optionally a check of what an exit 0 claims.  The verdict
of a case is ``pass`` or the list of what went wrong:

* ``traceback``: "Traceback (most recent call last)" on stdout or stderr;
* ``internal_error``: exit 1 (a bug by the table);
* ``exit_code``: another status than the case allows (bad input must be 2, Ctrl-C 130, ...);
* ``hang``: past the case's time limit with nothing printed; ``too_slow``: past it while printing (a refusal
  was expected, or the case is meant to be cheap);
* ``input_changed``: a file the case put in its folder (the inputs) has other bytes afterwards, or a file of
  the repository's ``benchmarks/`` changed;
* ``partial_output``: a final output name holds a file that does not read as its kind (npz, JSON, .blend,
  PNG, CSV, HTML), or an output exists after a refusal; ``leftover``: temporary, probe or lock files left;
* ``false_verdict``: exit 0 while the case's check says the claim contradicts the crafted input.

Full disks and read-only file systems are real: where ``unshare -m`` works (root, or user namespaces), the
case's ``mnt/`` folder is a small tmpfs in a private mount namespace, filled or remounted read-only, and its
contents are copied out after the command for the checks.  Elsewhere those cases are skipped.
Ctrl-C is SIGINT to the command's process group once it has printed something (it is working).

The matrix's modules beside this file: ``matrix_cases.py`` (``Case`` and ``build_cases``, the matrix),
``matrix_inputs.py`` (fixture texts and the makers of bad files), ``matrix_checks.py`` (checks of what an exit 0
claims).  This file runs the cases, classifies their outcomes and writes the results.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import hashlib
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path
from typing import Optional

import numpy as np

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:  # the matrix's modules beside this file, also when this file is loaded by its path
    sys.path.insert(0, str(HERE))

# the cases and their inputs; Case, OK, BAD and says are also reached through this module (the harness test)
from matrix_cases import BAD, OK, Case, build_cases  # noqa: E402,F401
from matrix_checks import says  # noqa: E402,F401
from matrix_inputs import OBJ_CUBE, REPO, SYNTH_SMALL, materialise  # noqa: E402


TRACEBACK = "Traceback (most recent call last)"


# --------------------------------------------------------------------------- fixtures (made once)
def _cli(*argv):
    return [sys.executable, "-m", "unipixie.cli", *argv]


BLOCK_SCENE = """
import sys, bpy
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0.0, 0.0, 1.0))
b = bpy.context.active_object; b.name = "Block"; b.scale = (0.6, 0.2, 0.2)
bpy.ops.object.transform_apply(scale=True)
bpy.ops.wm.save_as_mainfile(filepath=sys.argv[1])
"""


def make_fixtures(folder: Path, env: dict, blend: bool = True) -> None:
    """Small valid inputs every case copies: a measurement (npz, CSV + side-car), one with a strong hidden wind,
    a .blend with one object, a feature grid, a material field."""
    shutil.rmtree(folder, ignore_errors=True)  # a --work folder used before: made afresh
    folder.mkdir(parents=True, exist_ok=True)
    run = lambda cmd: subprocess.run(cmd, cwd=folder, env=env, capture_output=True, text=True, check=True)  # noqa: E731
    run(_cli("measure", "synth", "--out", "m.npz", *SYNTH_SMALL))
    run(_cli("measure", "convert", "m.npz", "m.csv"))
    run(_cli("measure", "synth", "--out", "wind.npz", "--effect", "wind:acceleration=0,6,0", "--noise", "0.0005",
             "--solver", "spring_mass", "--duration", "0.5", "--fps", "20", "--points", "30", "--setting", "anchors=32"))
    if blend:
        run([sys.executable, "-c", BLOCK_SCENE, str(folder / "scene.blend")])
    code = f"""
import numpy as np
from unipixie.core.types import FeatureGrid, GridGeometry, MaterialField
R = 64; occ = np.zeros((R, R, R), bool); occ[24:40, 28:36, 28:36] = True
geo = GridGeometry(resolution=R, origin=[-0.5, -0.5, -0.5], voxel_size=1 / R)
FeatureGrid(geo, occ, np.random.default_rng(0).normal(size=(int(occ.sum()), 32)).astype(np.float16),
            "offline-random-vit-w32").save("grid.npz")
MaterialField.homogeneous(geo, occ, 2e5, 0.3, 800.0).save("field.npz")
"""
    run([sys.executable, "-c", code])
    (folder / "cube.obj").write_text(OBJ_CUBE)


# --------------------------------------------------------------------------- outcome checks
def readable(p: Path) -> Optional[str]:
    """None when ``p`` reads as its kind, else why not."""
    try:
        if p.is_dir():
            for q in sorted(p.rglob("*")):
                if q.is_file() and not q.is_symlink():
                    why = readable(q)
                    if why:
                        return why
            return None
        data = p.read_bytes()
        if not data:
            return f"{p.name}: empty"
        ext = p.suffix.lower()
        if ext == ".npz":
            with zipfile.ZipFile(p) as z:
                bad = z.testzip()
                if bad:
                    return f"{p.name}: member {bad} corrupt"
            with np.load(p, allow_pickle=False) as d:
                for k in d.files:
                    d[k]
        elif ext == ".json":
            json.loads(data.decode("utf-8"))
        elif ext == ".blend":
            if data[:7] == b"BLENDER":
                if b"ENDB" not in data[-64:]:
                    return f"{p.name}: .blend without its end block"
            elif data[:4] != b"\x28\xb5\x2f\xfd":
                return f"{p.name}: not a .blend"
        elif ext == ".png":
            if not data.startswith(b"\x89PNG") or b"IEND" not in data[-16:]:
                return f"{p.name}: incomplete PNG"
        elif ext == ".csv":
            rows = data.decode("utf-8").splitlines()
            widths = {r.count(",") for r in rows if r and not r.startswith("#")}
            if len(widths) > 1:
                return f"{p.name}: ragged CSV"
        elif ext == ".html":
            if b"</html>" not in data[-200:].lower():
                return f"{p.name}: HTML cut off"
        return None
    except Exception as exc:  # noqa: BLE001 - any failure to read is the finding
        return f"{p.name}: {type(exc).__name__}: {exc}"[:200]


def digest(root: Path) -> dict:
    """sha256 of every regular file under ``root`` (links not followed), by relative path."""
    out = {}
    if not root.exists():
        return out
    for p in sorted(root.rglob("*")):
        if p.is_symlink() or not p.is_file():
            continue
        try:
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
        except OSError:
            pass
    return out


def is_leftover(name: str) -> bool:
    return (name.startswith(".") and (".tmp" in name or name.endswith(".unipixie-lock"))) or \
        name.startswith(".unipixie-probe")


# --------------------------------------------------------------------------- running one case
FS_SCRIPT = r"""
set -e
mount -t tmpfs -o size=$FM_SIZE tmpfs "$FM_MNT"
if [ -d "$FM_SEED" ]; then cp -a "$FM_SEED/." "$FM_MNT/"; fi
if [ "$FM_MODE" = full ]; then dd if=/dev/zero of="$FM_MNT/.fill" bs=4k 2>/dev/null || true; rm -f "$FM_MNT/.fill.small"; fi
if [ "$FM_MODE" = ro ]; then mount -o remount,ro "$FM_MNT"; fi
set +e
"$@"
rc=$?
mkdir -p "$FM_AFTER"
cp -a "$FM_MNT/." "$FM_AFTER/" 2>/dev/null
rm -f "$FM_AFTER/.fill"
exit $rc
"""


def fs_supported() -> bool:
    if not shutil.which("unshare"):
        return False
    with tempfile.TemporaryDirectory() as t:
        r = subprocess.run(["unshare", "-m", "--propagation", "private", "sh", "-c",
                            f"mount -t tmpfs -o size=64k tmpfs {t}"], capture_output=True)
        if r.returncode == 0:
            return True
        r = subprocess.run(["unshare", "-rm", "--propagation", "private", "sh", "-c",
                            f"mount -t tmpfs -o size=64k tmpfs {t}"], capture_output=True)
        return r.returncode == 0


def _preexec():
    signal.signal(signal.SIGINT, signal.SIG_DFL)  # as in a terminal (a background job starts with it ignored)
    try:
        if os.nice(0) < 10:
            os.nice(10 - os.nice(0))
    except OSError:
        pass


def _spawn(cmd, d: Path, env: dict, tag: str):
    out = open(d.parent / f"{d.name}.{tag}.out", "wb")
    err = open(d.parent / f"{d.name}.{tag}.err", "wb")
    proc = subprocess.Popen(cmd, cwd=d, env=env, stdout=out, stderr=err, stdin=subprocess.DEVNULL,
                            preexec_fn=_preexec, start_new_session=True)
    return proc, out, err


def run_case(case: Case, root: Path, fx: Path, base_env: dict, fs_ok: bool) -> dict:
    d = root / case.id
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    record = {"id": case.id, "command": " ".join(["unipixie", *case.argv[:2]]).strip(), "kind": case.kind,
              "argv": case.argv, "expected": list(case.expect), "note": case.note}
    if case.fs and not fs_ok:
        record.update(verdict="skipped", problems=["no private mount namespace here (unshare -m)"])
        return record
    files = dict(case.files)
    if case.fs:  # the seed of mnt/ is prepared outside; the command sees it inside the small tmpfs
        files = {(f"mnt_seed/{k[4:]}" if k.startswith("mnt/") else k): v for k, v in files.items()}
        (d / "mnt").mkdir()
    materialise(d, files, fx)
    before = digest(d)
    env = {**base_env, **case.env}
    argv = [a.replace("{d}", str(d)) for a in case.argv]
    cmd = _cli(*argv)
    if case.fs:
        env.update(FM_MNT=str(d / "mnt"), FM_SEED=str(d / "mnt_seed"), FM_AFTER=str(d / "mnt_after"),
                   FM_MODE=case.fs, FM_SIZE="1m" if case.fs == "full" else "4m")
        cmd = ["unshare", "-m", "--propagation", "private", "sh", "-c", FS_SCRIPT, "sh", *cmd]
    t0 = time.monotonic()
    procs = [_spawn(cmd, d, env, f"p{i}") for i in range(case.concurrent)]
    interrupted_at = None
    timed_out = False
    finished_before_interrupt = False
    try:
        if case.interrupt:
            proc, out, err = procs[0]
            after = max(case.interrupt_after, 4.0) if case.argv[:1] in (["bake"], ["features"], ["demo"], ["dataset"]) \
                else case.interrupt_after  # Blender's start-up first
            while proc.poll() is None and time.monotonic() - t0 < after:
                time.sleep(0.05)
            if proc.poll() is None:
                interrupted_at = round(time.monotonic() - t0, 2)
                os.killpg(proc.pid, signal.SIGINT)
                if case.interrupt_twice:
                    time.sleep(0.3)
                    if proc.poll() is None:
                        os.killpg(proc.pid, signal.SIGINT)
            else:
                finished_before_interrupt = True
        for proc, out, err in procs:
            left = max(1.0, case.timeout - (time.monotonic() - t0))
            try:
                proc.wait(timeout=left)
            except subprocess.TimeoutExpired:
                timed_out = True
                with_suppress(lambda: os.killpg(proc.pid, signal.SIGKILL))
                proc.wait()
    finally:
        for proc, out, err in procs:
            out.close(); err.close()
    wall = time.monotonic() - t0
    rcs = [p.returncode for p, _, _ in procs]
    texts = []
    for i in range(case.concurrent):
        o = Path(f"{d.parent / d.name}.p{i}.out").read_bytes().decode("utf-8", "replace")
        e = Path(f"{d.parent / d.name}.p{i}.err").read_bytes().decode("utf-8", "replace")
        texts.append((o, e))
    problems = []
    if any(TRACEBACK in o or TRACEBACK in e for o, e in texts):
        problems.append("traceback")
    if timed_out:
        printed = any((o + e).strip() for o, e in texts)
        problems.append("too_slow" if printed else "hang")
    else:
        for rc in rcs:
            if rc == 1:
                problems.append("internal_error")
            elif rc not in case.expect:
                problems.append("exit_code")
    if case.interrupt and (finished_before_interrupt or rcs[0] == -signal.SIGINT):
        # it had finished (or was finishing: the interpreter's shutdown restores the default handler) when the
        # signal came; the outputs must then be complete, which the checks below see
        problems.append("not_interrupted")
        problems = [p for p in problems if p != "exit_code"]
    # where the outputs are: mnt/ was a tmpfs; its contents after the command are in mnt_after/
    after_root = d
    view = (lambda rel: d / ("mnt_after/" + rel[4:] if rel.startswith("mnt/") else rel)) if case.fs else (lambda rel: d / rel)

    def unview(q: Path) -> str:  # the case's name of a file seen after the command (mnt_after/X is mnt/X)
        rel = str(q.relative_to(d))
        return "mnt/" + rel[len("mnt_after/"):] if case.fs and rel.startswith("mnt_after/") else rel
    after = digest(d)
    if case.fs:
        seed = {k[len("mnt_seed/"):]: v for k, v in before.items() if k.startswith("mnt_seed/")}
        now = {k[len("mnt_after/"):]: v for k, v in after.items() if k.startswith("mnt_after/")}
        before = {**{k: v for k, v in before.items() if not k.startswith("mnt_seed/")},
                  **{"mnt/" + k: v for k, v in seed.items()}}
        after = {**{k: v for k, v in after.items() if not k.startswith(("mnt_seed/", "mnt_after/"))},
                 **{"mnt/" + k: v for k, v in now.items()}}
    success = all(rc == 0 for rc in rcs) and not timed_out
    changed = []
    for rel, h in before.items():
        if after.get(rel) == h:
            continue
        if success and any(rel == o or rel.startswith(o.rstrip("/") + "/") for o in case.outputs + case.overwritten):
            continue
        if rel in case.overwritten and any(rc == 0 for rc in rcs):
            continue
        changed.append(rel)
    if changed:
        problems.append("input_changed")
    partial = []
    for rel in case.outputs:
        p = view(rel)
        existed = rel in before
        if not p.exists() and not p.is_symlink():
            continue
        if any(rc == 0 for rc in rcs) or existed or "not_interrupted" in problems:
            why = readable(p) if p.exists() else None
            if why and not (existed and after.get(rel) == before.get(rel)):
                partial.append(why)
        else:  # refused or cancelled: nothing new under the final name
            if p.is_dir():
                new = [q for q in p.rglob("*") if q.is_file() and unview(q) not in before and not is_leftover(q.name)]
                if new:
                    partial.append(f"{rel}: {len(new)} new file(s) after a refusal ({new[0].name})")
            elif p.is_file():
                partial.append(f"{rel}: present after a refusal")
    if partial:
        problems.append("partial_output")
    leftovers = [str(p.relative_to(d)) for p in d.rglob("*") if is_leftover(p.name)]
    if leftovers:
        problems.append("leftover")
    false_verdict = None
    if case.check is not None and success and not problems:
        try:
            false_verdict = case.check(d, texts)
        except Exception as exc:  # noqa: BLE001
            false_verdict = f"the check could not read the result: {type(exc).__name__}: {exc}"
        if false_verdict:
            problems.append("false_verdict")
    tail = lambda s: "\n".join(s.strip().splitlines()[-3:])[-600:]  # noqa: E731
    record.update(
        observed={"exit": rcs if case.concurrent > 1 else rcs[0], "wall_s": round(wall, 2),
                  "timed_out": timed_out, "interrupted_at_s": interrupted_at,
                  "stderr_tail": [tail(e) for _, e in texts] if case.concurrent > 1 else tail(texts[0][1]),
                  **({"changed_inputs": changed} if changed else {}),
                  **({"partial": partial} if partial else {}),
                  **({"leftovers": leftovers} if leftovers else {}),
                  **({"false_verdict": false_verdict} if false_verdict else {})},
        verdict="pass" if not problems else "inconclusive" if problems == ["not_interrupted"] else "fail",
        problems=sorted(set(problems)))
    if not problems:
        shutil.rmtree(d, ignore_errors=True)
        for i in range(case.concurrent):
            for ext in ("out", "err"):
                with_suppress(lambda: os.unlink(f"{d.parent / d.name}.p{i}.{ext}"))
    return record


def with_suppress(fn):
    try:
        fn()
    except OSError:
        pass


# --------------------------------------------------------------------------- the matrix
def summarise(records: list[dict]) -> dict:
    ran = [r for r in records if r["verdict"] != "skipped"]
    count = lambda p: sum(p in r.get("problems", []) for r in ran)  # noqa: E731
    kinds: dict = {}
    for r in records:
        k = kinds.setdefault(r["kind"], {"cases": 0, "pass": 0, "fail": 0, "skipped": 0, "inconclusive": 0})
        k["cases"] += 1
        k[r["verdict"]] += 1
    commands: dict = {}
    for r in records:
        c = commands.setdefault(r["command"].split()[1] if len(r["command"].split()) > 1 else "(none)",
                                {"cases": 0, "fail": 0})
        c["cases"] += 1
        c["fail"] += r["verdict"] == "fail"
    return {"cases": len(records), "ran": len(ran), "pass": sum(r["verdict"] == "pass" for r in ran),
            "fail": sum(r["verdict"] == "fail" for r in ran),
            "inconclusive": sum(r["verdict"] == "inconclusive" for r in ran), "skipped": len(records) - len(ran),
            "tracebacks": count("traceback"), "internal_errors": count("internal_error"),
            "wrong_exit_codes": count("exit_code"), "hangs_without_progress": count("hang"),
            "too_slow_with_progress": count("too_slow"), "inputs_damaged": count("input_changed"),
            "partial_outputs": count("partial_output"), "leftover_temporary_files": count("leftover"),
            "exit_0_with_false_verdict": count("false_verdict"), "not_interrupted": count("not_interrupted"),
            "by_kind": kinds, "by_command": commands}


def _git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    except OSError:
        return ""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", help="write the results (benchmarks.md format) to this JSON file")
    ap.add_argument("--only", action="append", default=[], help="run only cases whose id starts with this (repeatable)")
    ap.add_argument("--ids", help="comma-separated case ids to run")
    ap.add_argument("--jobs", type=int, default=2, help="cases at once (default 2)")
    ap.add_argument("--work", help="keep the case folders here (default: a temporary folder, failed cases kept)")
    ap.add_argument("--list", action="store_true", help="print the cases and exit")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)

    cases = build_cases()
    if args.only:
        cases = [c for c in cases if any(c.id.startswith(p) for p in args.only)]
    if args.ids:
        wanted = set(args.ids.split(","))
        cases = [c for c in cases if c.id in wanted]
    if args.list:
        for c in cases:
            print(f"{c.id:55s} {c.kind:26s} expect {c.expect}  unipixie {' '.join(c.argv)}")
        print(f"{len(cases)} cases")
        return 0
    root = Path(args.work or tempfile.mkdtemp(prefix="unipixie-fault-matrix-"))
    root.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env.setdefault("PYTHONPATH", str(REPO.parent))
    env["UNIPIXIE_CACHE_DIR"] = str(root / "cache")
    env.setdefault("UNIPIXIE_WARP_CACHE", str(Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
                                              / "unipixie" / "warp"))
    env["BLENDER_USER_RESOURCES"] = str(root / "blender-user")
    env.pop("UNIPIXIE_TRACEBACK", None)
    env["PYTHONUNBUFFERED"] = "1"
    fx = root / "fixtures"
    t0 = time.time()
    make_fixtures(fx, env)
    fs_ok = fs_supported()
    bench_before = digest(REPO / "benchmarks")
    records = []
    with cf.ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futures = {pool.submit(run_case, c, root / "cases", fx, env, fs_ok): c for c in cases}
        for fut in cf.as_completed(futures):
            c = futures[fut]
            try:
                r = fut.result()
            except Exception as exc:  # noqa: BLE001 - the harness's own failure is reported as such
                r = {"id": c.id, "command": "unipixie " + " ".join(c.argv[:2]), "kind": c.kind, "argv": c.argv,
                     "expected": list(c.expect), "verdict": "fail", "problems": ["harness_error"],
                     "observed": {"error": f"{type(exc).__name__}: {exc}"}}
            records.append(r)
            if not args.quiet:
                print(f"[{len(records):3d}/{len(cases)}] {r['verdict']:7s} {r['id']:55s} "
                      f"{','.join(r.get('problems', []))} exit {r.get('observed', {}).get('exit')}", flush=True)
    bench_after = digest(REPO / "benchmarks")
    if args.out:
        bench_after.pop(str(Path(args.out).resolve().relative_to(REPO / "benchmarks"))
                        if str(Path(args.out).resolve()).startswith(str(REPO / "benchmarks")) else "", None)
        bench_before.pop(str(Path(args.out).resolve().relative_to(REPO / "benchmarks"))
                         if str(Path(args.out).resolve()).startswith(str(REPO / "benchmarks")) else "", None)
    records.sort(key=lambda r: r["id"])
    summary = summarise(records)
    summary["repository_benchmarks_changed"] = sorted(k for k in set(bench_before) | set(bench_after)
                                                     if bench_before.get(k) != bench_after.get(k))
    summary["wall_s"] = round(time.time() - t0, 1)
    summary["work_folder"] = str(root)
    print(json.dumps({k: v for k, v in summary.items() if not isinstance(v, dict)}, indent=1))
    if args.out:
        load = open("/proc/loadavg").read().split()[:3] if os.path.exists("/proc/loadavg") else []
        device = f"{platform.processor() or platform.machine()} ({os.cpu_count()} cores)"
        try:
            for line in open("/proc/cpuinfo"):
                if line.startswith("model name"):
                    device = f"{line.split(':', 1)[1].strip()} ({os.cpu_count()} cores)"
                    break
        except OSError:
            pass
        doc = {"benchmark": "fault_matrix", "commit": _git_commit(), "date": time.strftime("%Y-%m-%d"),
               "results": [{"case": "issue 20 fault matrix: all cases", "device": device, "metric": "cases_failed",
                            "value": summary["fail"], "runs": 1,
                            "load_average_at_end": load, "summary": summary}],
               "cases": records}
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(args.out).with_suffix(".tmp.json")
        tmp.write_text(json.dumps(doc, indent=1, default=str) + "\n")
        os.replace(tmp, args.out)
        print(f"wrote {args.out}")
    return 0 if summary["fail"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
