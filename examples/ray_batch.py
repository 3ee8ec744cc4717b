#!/usr/bin/env python3
"""Run a batch of captures on Ray: one `aim batch MANIFEST --out ROOT --index I`
process per capture, as a Ray task of its own, then the batch's summary.

    python3 examples/ray_batch.py MANIFEST --out ROOT [--aim PATH]
        [--address ray://HEAD:10001 | --num-cpus N] [--cpus-per-capture K]
        [--retries R] [-- EXTRA aim batch ARGUMENTS]

aim does the work and keeps the state: each capture's folder ROOT/NAME holds its
status.json and checkpoints, so a task that runs a capture again (after its
worker was stopped or died) resumes it, and one that finds it done returns at
once. On a cluster, MANIFEST, its inputs and ROOT must be on a file system every
node sees, and `aim` on every node's PATH (or --aim). docs/scale.md.

Exit status: 0 when every capture is done, 1 otherwise.
"""

import argparse
import json
import os
import subprocess
import sys

import ray

# aim batch's exit codes (docs/scale.md).
DONE, INPUT_UNUSABLE, INTERRUPTED, INTERNAL, BUSY = 0, 3, 4, 5, 6


@ray.remote
def run_capture(aim, manifest, root, index, name, threads, retries, extra):
    """One capture, by its own aim process; run again (resuming) when that was
    interrupted, killed or failed internally, up to `retries` times."""
    attempts = []
    for _ in range(retries + 1):
        cmd = [aim, "batch", manifest, "--out", root, "--index", str(index), "--threads", str(threads), *extra]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        attempts.append(proc.returncode)
        # A negative code: killed by that signal; resuming from the checkpoints is what helps.
        if proc.returncode not in (INTERRUPTED, INTERNAL) and proc.returncode >= 0:
            break
    status_path = os.path.join(root, name, "status.json")
    status = None
    if os.path.exists(status_path):
        with open(status_path) as f:
            status = json.load(f)
    return {
        "index": index,
        "name": name,
        "exit_codes": attempts,
        "status": status,
        "log_tail": (proc.stdout + proc.stderr)[-2000:],
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("manifest")
    parser.add_argument("--out", required=True, help="the batch's folder ROOT")
    parser.add_argument("--aim", default="aim", help="the aim binary (default: aim on PATH)")
    parser.add_argument("--address", default=None, help="a Ray cluster to join (default: start a local instance)")
    parser.add_argument("--num-cpus", type=int, default=None, help="CPUs of the local instance (default: all)")
    parser.add_argument("--cpus-per-capture", type=int, default=1, help="CPUs (and aim threads) per capture")
    parser.add_argument("--retries", type=int, default=2, help="reruns of an interrupted, killed or failed capture")
    parser.add_argument("extra", nargs="*", help="more `aim batch` arguments, after --")
    args = parser.parse_args()

    manifest = os.path.abspath(args.manifest)
    root = os.path.abspath(args.out)
    listed = subprocess.run([args.aim, "batch", manifest, "--list"], capture_output=True, text=True)
    if listed.returncode != 0:
        sys.exit(f"{args.aim} batch {manifest} --list: {listed.stderr.strip()}")
    captures = json.loads(listed.stdout)

    if args.address:
        ray.init(address=args.address)
    else:
        ray.init(num_cpus=args.num_cpus, include_dashboard=False)
    task = run_capture.options(num_cpus=args.cpus_per_capture)
    pending = [
        task.remote(args.aim, manifest, root, c["index"], c["name"], args.cpus_per_capture, args.retries, args.extra)
        for c in captures
    ]
    all_done = True
    while pending:
        ready, pending = ray.wait(pending, num_returns=1)
        for result in ray.get(ready):
            state = (result["status"] or {}).get("state", "no status")
            error = (result["status"] or {}).get("error") or ""
            print(f"capture {result['index']} ({result['name']}): {state}, exit codes {result['exit_codes']} {error}")
            if state != "done":
                all_done = False
                print(result["log_tail"], file=sys.stderr)
    ray.shutdown()

    summary = subprocess.run([args.aim, "batch", "--summary", root], capture_output=True, text=True)
    print(summary.stdout, end="")
    if summary.returncode != 0:
        print(summary.stderr, file=sys.stderr)
        all_done = False
    sys.exit(0 if all_done else 1)


if __name__ == "__main__":
    main()
