"""``mi-shadowgs batch SPEC --out DIR``: many captures (photos or datasets), each an import
and a run, as Ray tasks on this machine or a cluster; ``DIR/batch.csv`` and
``DIR/batch.html`` hold one row per item. Run again, finished items are reused and
interrupted ones continue (docs/cluster.md).
"""

from __future__ import annotations

import argparse
import os

from mi_shadowgs.cli.run import SET_HELP
from mi_shadowgs.config import PRESET_NAMES


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("spec", help="a folder of captures (one sub-folder each: photos, "
                        "photos/ and masks/, a transforms.json, or a dataset) or a .toml/.json "
                        "file listing items (source, name, preset, set, seed, variant, cpus, "
                        "masks)")
    parser.add_argument("--out", required=True,
                        help="batch folder: DIR/NAME/{data,run} per item, batch.csv, "
                             "batch.html (run again: finished items are reused)")
    parser.add_argument("--address", default=None,
                        help="the Ray cluster to run on: HOST:6379, ray://HOST:10001 or auto "
                             "(default: a local Ray runtime on this machine)")
    parser.add_argument("--workers", type=int, default=None,
                        help="items at once on the local runtime (default: this machine's "
                             "cores / --cpus-per-item)")
    parser.add_argument("--cpus-per-item", type=int, default=None, metavar="N",
                        help="each item's CPUs on Ray and Dr.Jit threads (default 1; one "
                             "thread gives the same bytes every time)")
    parser.add_argument("--preset", default=None,
                        help=f"every item's preset unless the spec names one: "
                             f"{', '.join(PRESET_NAMES)} (default cpu-small)")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                        dest="settings", help="for every item: " + SET_HELP)
    parser.add_argument("--seed", type=int, default=None,
                        help="every item's seed unless the spec names one (default 0)")
    parser.add_argument("--retries", type=int, default=3,
                        help="times an item whose worker is lost is tried again (default 3)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def run(args) -> int:
    from mi_shadowgs.backend import VARIANT_ENV
    from mi_shadowgs.batch import runner, spec
    from mi_shadowgs.cli import CLIError

    for flag, value in (("--workers", args.workers), ("--cpus-per-item", args.cpus_per_item)):
        if value is not None and value < 1:
            raise CLIError(f"{flag} must be >= 1, got {value}")
    if args.retries < 0:
        raise CLIError(f"--retries must be >= 0, got {args.retries}")
    try:
        runner.import_ray()
    except runner.RayMissing as exc:
        raise CLIError(str(exc)) from None
    # --variant (or $MI_SHADOWGS_VARIANT) is the items' backend, not this process's
    defaults = {"preset": args.preset, "set": args.settings, "seed": args.seed,
                "variant": args.variant or os.environ.get(VARIANT_ENV) or None,
                "cpus": args.cpus_per_item}
    items = spec.read_spec(args.spec, args.out, defaults)
    runner.claim_batch_folder(args.out, args.spec, items)
    cpus = None if args.workers is None else args.workers * (args.cpus_per_item or 1)
    rows = runner.run_batch(items, args.out, address=args.address, num_cpus=cpus,
                            retries=args.retries, progress=not args.no_progress, lock=False)
    failed = [r for r in rows if r["status"] not in runner.OK]
    done = {s: sum(r["status"] == s for r in rows) for s in runner.OK}
    print(f"batch: {done['finished']} finished, {done['reused']} reused, {len(failed)} "
          f"failed of {len(rows)}; {args.out}/batch.html")
    for r in failed:
        print(f"  {r['name']}: {r['error']}")
    return 1 if failed else 0
