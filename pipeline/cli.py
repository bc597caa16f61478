"""`blunf` / `python -m pipeline`: run, synth, batch, bench, import, render, studio, clean.

User errors (BlunfError, a bad argument, a missing file) end with one line naming the file or
value at fault and exit status 2; nothing half-written is left in the cache.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path

from pipeline.runtime import Terminated, request_stop, setup_runtime, stop_if_requested
from stages.common.errors import BlunfError
from stages.common.io import finite_json
from stages.common.progress import configure as configure_progress

log = logging.getLogger("blunf")


def _size(s: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in s.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--size {s!r}: expected WxH, e.g. 320x240") from None
    if w < 8 or h < 8 or w > 8192 or h > 8192:
        raise argparse.ArgumentTypeError(f"--size {s!r}: each side must be in 8..8192")
    return w, h


def _views(s: str) -> tuple[int, ...]:
    try:
        v = tuple(int(x) for x in s.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--views {s!r}: expected counts, e.g. 60,120") from None
    if not v or min(v) < 2:
        raise argparse.ArgumentTypeError(f"--views {s!r}: each count must be >= 2")
    return v


def _positive(s: str) -> int:
    try:
        v = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not an integer") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"{s!r} must be >= 1")
    return v


def _whole(s: str) -> int:
    try:
        return int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not a whole number") from None


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"blunf: error: {message}\n")


def parser() -> argparse.ArgumentParser:
    p = _Parser(prog="blunf", description="Photos of an indoor scene to an editable blueprint.")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="cmd", required=True, parser_class=_Parser)

    r = sub.add_parser("run", help="build the blueprint of a capture")
    r.add_argument("capture", type=Path)
    r.add_argument("--out", type=Path, required=True, help="run folder (cache, report, outputs)")
    r.add_argument("--config", type=Path, help="YAML overriding the defaults (configs/*.yaml)")
    r.add_argument("--set", dest="sets", action="append", default=[], metavar="STAGE.KEY=VALUE")
    r.add_argument("--edits", type=Path, help="edit spec (YAML)")
    r.add_argument("--frames", type=_positive, help="use N views spread along the capture")
    r.add_argument("--quiet", action="store_true", help="no progress bars or progress lines")

    s = sub.add_parser("synth", help="make a procedural room with exact ground truth")
    s.add_argument("out", type=Path)
    s.add_argument("--views", type=_positive, default=60)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--size", type=_size, default=(320, 240), help="WxH (default 320x240)")
    s.add_argument(
        "--photos-only",
        action="store_true",
        help="keep only images and intrinsics, as a phone gives (ground truth still in gt/)",
    )
    s.add_argument("--doors", type=int, default=0, help="door gaps in distinct walls (0..4)")
    s.add_argument(
        "--passages", type=int, default=0, help="passages (wider gaps) in other walls (0..4)"
    )
    s.add_argument("--shape", choices=("rect", "L"), default="rect", help="room outline")
    s.add_argument("--rooms", type=_whole, default=1,
                   help="1: one room; 2..5: a home of that many rooms, doors between")  # fmt: skip
    s.add_argument(
        "--realism",
        default="none",
        help="honest | surfaces=plain,exposure=STOPS,blur=PX,noise=SD (stages/synth/realism.py)",
    )

    b = sub.add_parser("bench", help="run time against error: table, CSV and plots")
    b.add_argument("--out", type=Path, help="default runs/bench (--targets: runs/targets)")
    b.add_argument("--quick", action="store_true", help="a small grid (minutes)")
    b.add_argument("--repeats", type=_positive, help="runs per variant (default 1 quick, 3 full)")
    b.add_argument("--threads", type=_positive,
                   help="CPU threads a run (default 1; --targets: the run's own)")  # fmt: skip
    b.add_argument("--targets", action="store_true",
                   help="each speed target's figure, reference and ratio (targets.md)")  # fmt: skip
    b.add_argument("--only", metavar="1,5,7", help="with --targets: the targets to measure")
    b.add_argument("--scale", action="store_true",
                   help="cost curve: each stage's seconds, CPU-s, memory by views")  # fmt: skip
    b.add_argument("--views", type=_views, default=(60, 120, 240, 480),
                   help="with --scale: view counts (default 60,120,240,480)")  # fmt: skip
    b.add_argument("--rooms", type=_positive, default=1, help="with --scale: rooms (1..5)")
    b.add_argument("--size", type=_size, default=(320, 240), help="with --scale: WxH")
    b.add_argument("--seed", type=int, default=0, help="with --scale: the scene's seed")
    b.add_argument("--photos-only", action="store_true",
                   help="with --scale: images only (SfM poses, depth from the photos)")  # fmt: skip
    b.add_argument("--config", type=Path, help="with --scale: YAML for every run")
    b.add_argument("--set", dest="sets", action="append", default=[], metavar="STAGE.KEY=VALUE")

    a = sub.add_parser("batch", help="run many captures as Dask tasks (local or a cluster)")
    a.add_argument("captures", nargs="+", type=Path, metavar="CAPTURE")
    a.add_argument("--out", type=Path, required=True, help="batch folder: OUT/<scene>/ per run")
    a.add_argument("--scheduler", metavar="ADDRESS", help="tcp://host:8786 of a running cluster")
    a.add_argument("--workers", type=_positive, help="local worker processes (default: cores)")
    a.add_argument("--threads-per-worker", type=_positive, default=1, metavar="T")
    a.add_argument("--dashboard", default="127.0.0.1:8787", help="local dashboard; 'none': off")
    a.add_argument("--config", type=Path, help="YAML overriding the defaults (configs/*.yaml)")
    a.add_argument("--set", dest="sets", action="append", default=[], metavar="STAGE.KEY=VALUE")
    a.add_argument("--edits", type=Path, help="edit spec (YAML), for every capture")
    a.add_argument("--quiet", action="store_true", help="no progress lines (nor in the logs)")

    i = sub.add_parser("import", help="convert another layout into a blunf capture")
    i.add_argument("kind", help="7scenes, replica-vmap, colmap, nerfstudio, photos, video")
    i.add_argument("src", type=Path)
    i.add_argument("out", type=Path)
    i.add_argument("--frames", type=_positive, help="video: frames kept (default: by length)")
    i.add_argument("--max-side", type=_positive, help="video: longer side of the frames written")

    v = sub.add_parser("render", help="one view of a run's NeRF, with edits applied")
    v.add_argument("run_dir", type=Path)
    v.add_argument("--view", type=int, help="an input view's index")
    v.add_argument("--camera", type=Path, help="JSON: 4x4 camera-to-world pose, intrinsics")
    v.add_argument("--edits", type=Path, help="edit spec (YAML)")
    v.add_argument("--scale", type=float, default=1.0, help="fraction of the resolution")
    v.add_argument("--out", type=Path, required=True, help="PNG to write")
    v.add_argument("--fast", action="store_true",
                   help="ray-cast the fused mesh, the field asked near its hits (the studio's "
                   "preview), instead of the volume render")  # fmt: skip

    t = sub.add_parser("studio", help="edit a run in the browser (local web page)")
    t.add_argument("run_dir", type=Path)
    t.add_argument("--port", type=int, default=8080)
    t.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default local; any address needs the token of "
                   "the URL it prints, as the local one does)")  # fmt: skip

    c = sub.add_parser("clean", help="drop the cache entries the latest run did not use")
    c.add_argument("run_dir", type=Path)
    return p


def main(argv: list[str] | None = None) -> int:
    try:
        args = parser().parse_args(argv)
    except SystemExit as e:  # a bad argument (one line already printed) or --help
        return 0 if e.code is None else e.code if isinstance(e.code, int) else 2
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )
    if not args.verbose:  # ezdxf logs a line per DXF dictionary it creates: 26 per run
        logging.getLogger("ezdxf").setLevel(logging.WARNING)
    # bars on a terminal, else a log line every ~10 % (stages/common/progress.py)
    configure_progress("off" if getattr(args, "quiet", False) else "auto")
    if argv is None and args.cmd in ("run", "batch", "import", "bench"):
        _terminate_quietly()
    try:
        code = _dispatch(args)
        stop_if_requested()  # a SIGTERM whose raise a finaliser swallowed in the last stage
        return code
    except BlunfError as e:
        print(f"blunf: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # a write failure no stage turned into a BlunfError
        from pipeline.publish import write_error

        err = write_error(e, "?")
        if err is None:
            raise
        print(f"blunf: error: {err}", file=sys.stderr)
        return 2
    except Terminated:
        return _stopped("blunf: terminated", 143, argv is None)
    except KeyboardInterrupt:
        return _stopped("blunf: interrupted", 130, argv is None)


def _stopped(line: str, code: int, leave: bool) -> int:
    """One line for Ctrl-C or SIGTERM, then `code`. The command (`leave`: main called with
    no argv) exits at once: the runner has removed its temp folders by now, and once in CI,
    under load, a Ctrl-C that had printed its line still ended the process by SIGINT (-2)
    rather than 130, in the interpreter's shutdown that os._exit skips."""
    print(line, file=sys.stderr)
    if not leave:
        return code
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def _terminate_quietly() -> None:
    """pycolmap installs glog's failure handler when imported, which prints ~30 lines of
    native stack on SIGTERM: import it first, then take SIGTERM back."""
    import signal

    try:
        import pycolmap  # noqa: F401
    except ImportError:
        pass

    def terminated(signum: int, frame: object) -> None:
        request_stop()

    signal.signal(signal.SIGTERM, terminated)


def _dispatch(args: argparse.Namespace) -> int:
    if args.cmd == "run":
        from pipeline.config import load_config
        from stages.common.io import check_exists

        sets = list(args.sets)
        if args.frames:
            sets.append(f"ingest.frames={args.frames}")
        cfg = load_config(args.config, sets)
        if args.edits is not None and not args.edits.is_file():
            raise BlunfError(f"{args.edits}: edit spec not found")
        if cfg["ingest"].kind == "auto":
            # the layout read before the run folder is made (it checks the path too): a plain
            # file or an empty folder leaves nothing behind
            from stages.ingest import detect

            detect(args.capture)
        else:
            check_exists(args.capture, "capture folder")
        # the stages (torch, Open3D: ~3 s) once the arguments are known to be good
        from pipeline.run import run

        n = setup_runtime(cfg.run.threads)
        log.debug("threads: %d", n)
        report = run(args.capture, args.out, cfg, args.edits)
        summary = finite_json(dict(report.metrics))  # strict JSON: NaN as null
        print(
            json.dumps(
                {
                    "blueprint": str(args.out / "blueprint.png"),
                    "report": str(args.out / "report.json"),
                    "report_html": str(args.out / "report.html"),
                    "stages": {f"{s.name}:{s.impl}": s.status for s in report.stages},
                    "metrics": summary,
                },
                indent=1,
                allow_nan=False,
            ),
            flush=True,
        )
        # the stages' warnings again, where the progress lines cannot bury them, and the
        # page to open, last (on stderr: stdout stays one JSON document)
        from pipeline.report_html import warnings

        for stage, w in warnings(report.to_json()):
            print(f"warning: {stage}: {w}", file=sys.stderr)
        print(
            f"report: {Path(os.path.abspath(args.out / 'report.html')).as_uri()}", file=sys.stderr
        )
        return 0
    if args.cmd == "synth":
        from stages.synth import make_room
        from stages.synth.realism import Realism

        setup_runtime()
        out = make_room(
            args.out,
            views=args.views,
            seed=args.seed,
            size=args.size,
            photos_only=args.photos_only,
            doors=args.doors,
            passages=args.passages,
            shape=args.shape,
            realism=Realism.parse(args.realism),
            rooms=args.rooms,
        )
        print(out)
        return 0
    if args.cmd == "import":
        from stages.ingest import import_capture
        from stages.ingest.video import VideoOptions

        video = VideoOptions(args.frames or 0, args.max_side or 0)
        print(import_capture(args.kind, args.src, args.out, video))
        return 0
    if args.cmd == "batch":
        from pipeline.batch import BatchOptions, batch

        opts = BatchOptions(
            out=args.out,
            scheduler=args.scheduler,
            workers=args.workers or 0,
            threads_per_worker=args.threads_per_worker,
            config=args.config,
            sets=tuple(args.sets),
            edits=args.edits,
            dashboard=None if args.dashboard.lower() == "none" else args.dashboard,
            quiet=args.quiet,
        )
        facts = batch(list(args.captures), opts)
        print(json.dumps({k: v for k, v in facts.items() if k != "outcomes"}, indent=1))
        return 0 if facts["failed"] == 0 else 1
    if args.cmd == "bench":
        if args.scale:
            from pipeline.bench.curve import scale_bench, table

            setup_runtime(args.threads or 1)
            out = args.out or Path("runs/scale")
            r = scale_bench(
                out,
                args.views,
                args.rooms,
                args.seed,
                args.size,
                args.photos_only,
                args.threads or 1,
                args.config,
                args.sets,
            )
            print(table(r))
            print(f"{out / 'scale.json'}, {out / 'scale.md'}, {out / 'scale.svg'}")
            return 0
        if args.sets or args.config:
            raise BlunfError("--set and --config apply to --scale runs only")
        if args.targets:
            from pipeline.bench.targets import parse_only, targets

            only = parse_only(args.only)  # a bad list fails before any work
            setup_runtime(args.threads or 0)
            out = args.out or Path("runs/targets")
            print(targets(out, args.quick, args.repeats, args.threads or 0, only))
            return 0
        if args.only:
            raise BlunfError("--only picks targets: use it with --targets")
        from pipeline.bench import bench

        setup_runtime(args.threads or 1)
        out = args.out or Path("runs/bench")
        print(bench(out, quick=args.quick, repeats=args.repeats, threads=args.threads or 1))
        return 0
    if args.cmd == "render":
        from pipeline.render import render_command

        _check_out_file(args.out)
        setup_runtime()
        r = render_command(
            args.run_dir, args.view, args.camera, args.edits, args.scale, args.out, args.fast
        )
        print(json.dumps(r))
        return 0
    if args.cmd == "studio":
        from pipeline.studio import serve

        setup_runtime()
        return serve(args.run_dir, args.host, args.port)
    if args.cmd == "clean":
        from pipeline.clean import clean

        freed, n = clean(args.run_dir)
        print(f"freed {freed / 1e6:.1f} MB ({n} entries)")
        return 0
    raise BlunfError(f"unknown command {args.cmd!r}")


def _check_out_file(out: Path) -> None:
    """`--out` names a picture to write into an existing folder (checked before any work)."""
    if out.is_dir():
        raise BlunfError(f"{out}: is a folder; --out names the picture to write (view.png)")
    if not out.parent.is_dir():
        raise BlunfError(f"{out.parent}: folder not found (--out {out})")
