"""``make sanitize``: the C under AddressSanitizer + UndefinedBehaviorSanitizer and under ThreadSanitizer.

Builds, for each sanitizer, the servo core with

- ``examples/c/haptic_loop.c`` (the C example: its scripted session, and its ``--thread`` mode with the device
  in the library's callbacks),
- ``tests/c/servo_threads.c`` (thread mode beside three application threads calling set_probes, read, state
  and deformation; then two threads exchanging a trace tick-synchronously; then a table over the file's own
  sections, ``pm_table_from_sections``, stepped against the loaded one; then those sections less the ζ table,
  coupled through a pair function, ``pm_servo_create_paired``, stepped and exchanged against the loaded one;
  then a table exported from a compressed artifact of the same kidney, whose contacts the core couples from Ξ's
  compressed sections, against the ζ table's),

and the selected inversion with ``tests/c/selinv_driver.c`` (its page-fault helper thread, a cancel from a
second thread, damaged factor arrays), over a runtime table exported from a small kidney artifact built here.
Every program runs with ``halt_on_error`` and a distinct exit code: any report fails the run (exit 1), and
the report is printed.  ThreadSanitizer's suppressions (``tsan.supp``) name third-party libraries only
(OpenMP in CHOLMOD, OpenBLAS's workers: uninstrumented, their synchronisation invisible to it).
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
SANITIZERS = {"address+undefined": ["-fsanitize=address,undefined", "-fno-sanitize-recover=undefined",
                                    "-fno-omit-frame-pointer"],
              "thread": ["-fsanitize=thread"]}
ENV = {"address+undefined": {"ASAN_OPTIONS": "halt_on_error=1:exitcode=66:detect_leaks=1",
                             "UBSAN_OPTIONS": "halt_on_error=1:exitcode=66:print_stacktrace=1",
                             "LSAN_OPTIONS": f"suppressions={HERE / 'lsan.supp'}"},
       "thread": {"TSAN_OPTIONS": f"halt_on_error=1:exitcode=66:suppressions={HERE / 'tsan.supp'}"}}


def main() -> int:
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    servo = ROOT / "runtime" / "servo"
    core = sorted(str(p) for p in (servo / "core").glob("*.c"))
    suitesparse = os.environ.get("PMASK_SUITESPARSE_INCLUDE", "/usr/include/suitesparse")
    work = Path(tempfile.mkdtemp(prefix="pmask-sanitize-"))
    failed = []
    try:
        art, table = work / "kidney.h5", work / "kidney.tbl"
        pmask = [sys.executable, "-m", "pmask.pipeline"]
        # (the same r_max for both: the contact region's taper follows it, and part 5 compares their forces)
        subprocess.run([*pmask, "-q", "precompute", "kidney", "--size", "0.009", "--r-max", "0.01", "-o", str(art)],
                       check=True, stdout=subprocess.DEVNULL)
        subprocess.run([*pmask, "export-table", str(art), "-o", str(table)], check=True, stdout=subprocess.DEVNULL)
        comp, ctable = work / "kidney-compressed.h5", work / "kidney-compressed.tbl"
        subprocess.run([*pmask, "-q", "precompute", "kidney", "--size", "0.009", "--r-max", "0.01", "--compress",
                        "--workers", "2", "-o", str(comp)], check=True, stdout=subprocess.DEVNULL)
        subprocess.run([*pmask, "export-table", str(comp), "-o", str(ctable)], check=True, stdout=subprocess.DEVNULL)
        programs = {
            "haptic_loop": ([str(ROOT / "examples/c/haptic_loop.c"), *core], [f"-I{servo}"], [], [[str(table)],
                                                                                              [str(table), "--thread"]]),
            "servo_threads": ([str(HERE / "servo_threads.c"), *core], [f"-I{servo}"], [], [[str(table), str(ctable)]]),
            "selinv_driver": ([str(HERE / "selinv_driver.c"), str(ROOT / "precompute/_selected_inverse.c")],
                              [f"-I{suitesparse}"], ["-lcholmod", "-llapack", "-lblas"], [[]]),
        }
        for san, flags in SANITIZERS.items():
            for name, (sources, inc, libs, runs) in programs.items():
                exe = work / f"{name}-{san.split('+')[0]}"
                build = [cc, "-std=c99", "-g", "-O1", "-Wall", "-Wextra", "-Werror", "-ffp-contract=off", *flags, *inc,
                         *sources, *libs, "-lm", "-lpthread", "-o", str(exe)]
                r = subprocess.run(build, capture_output=True, text=True)
                if r.returncode:
                    print(f"{name} ({san}): does not build\n{r.stderr}")
                    failed.append(f"{name} build ({san})")
                    continue
                for args in runs:
                    env = dict(os.environ, OMP_NUM_THREADS="2", **ENV[san])
                    r = subprocess.run([str(exe), *args], capture_output=True, text=True, env=env, timeout=600)
                    label = f"{name} {' '.join(a for a in args if a.startswith('--'))}".strip() + f" ({san})"
                    if r.returncode:
                        print(f"FAIL {label}: exit {r.returncode}\n{r.stdout[-2000:]}{r.stderr[-6000:]}")
                        failed.append(label)
                    else:
                        last = (r.stdout.strip().splitlines() or [""])[-1]
                        print(f"ok   {label}: {last}")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if failed:
        print(f"make sanitize: {len(failed)} failed: {', '.join(failed)}")
        return 1
    print("make sanitize: no sanitizer reports")
    return 0


if __name__ == "__main__":
    sys.exit(main())
