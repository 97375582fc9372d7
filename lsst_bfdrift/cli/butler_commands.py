"""``bfdrift butler-put``: FITS exposures into a Butler repository's run collection,
the step between ``butler create`` and ``pipetask run`` (options and command).

The work is :func:`~lsst_bfdrift.pipeline.ingest.put_exposures`; the LSST
middleware (the ``[lsst]`` extra) is imported only when the command runs, so
``bfdrift`` works without it.
"""

import os

from lsst_bfdrift.cli._common import add_common_options, print_json
from lsst_bfdrift.utils.errors import InputError
from lsst_bfdrift.utils.progress import ProgressBar

__all__ = ["add_butler_put_parser", "cmd_butler_put"]


def _middleware():
    """The ingest module, or an error saying which extra to install."""
    try:
        from lsst_bfdrift.pipeline import ingest
    except ImportError as exc:
        raise InputError("bfdrift butler-put needs the LSST middleware: pip install "
                         f"'lsst_bfdrift[lsst]' ({exc})") from None
    return ingest


def cmd_butler_put(args):
    """``bfdrift butler-put``: register and put FITS exposures with their data IDs.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status.
    """
    ingest = _middleware()
    if not os.path.isdir(args.repo):
        raise InputError(f"{args.repo}: no such repository; make one first: butler create "
                         f"{args.repo} --seed-config $(python -c \"import lsst_bfdrift.pipeline "
                         "as p; print(p.seed_config_path())\")")
    data_ids = None if not args.data_id else [ingest.parse_data_id(t) for t in args.data_id]
    with ProgressBar(len(args.files), f"butler-put: {len(args.files)} file(s) into {args.run}",
                     enabled=not args.quiet) as bar:
        bar.show()
        kw = {} if args.dataset_type is None else {"dataset_type": args.dataset_type}
        done = ingest.put_exposures(args.repo, args.files, run=args.run,
                                    instrument=args.instrument, data_ids=data_ids,
                                    physical_filter=args.filter,
                                    progress=lambda k, n: bar(k - bar.done), **kw)
    if args.json:
        print_json({"repo": os.path.abspath(args.repo), "run": args.run, "files": done})
        return 0
    for d in done:
        ids = ", ".join(f"{k}={v}" for k, v in d["data_id"].items())
        print(f"{d['file']} -> {d['dataset_type']} ({ids}) in {d['run']}")
    print(f"next: pipetask run -b {args.repo} -i {args.run} -o OUTPUT_RUN "
          "--register-dataset-types -p $(python -c \"import lsst_bfdrift.pipeline as p; "
          "print(p.pipeline_path())\")")
    return 0


def add_butler_put_parser(subparsers):
    """Add ``butler-put`` to ``subparsers`` (the ``bfdrift`` subcommands); return its parser."""
    p = subparsers.add_parser(
        "butler-put", help="put FITS exposures into a Butler run collection (for pipetask)",
        description="Put FITS exposures (electrons; LSST Exposure, CCDData or plain layout) "
        "into a run collection of a Butler repository made with the package's seed config, "
        "as the pipeline's input dataset type (post_isr_image: instrument, exposure, "
        "detector), recording the instrument, detectors and exposures of their data IDs if "
        "the repository does not know them. Then: pipetask run -b REPO -i RUN ...")
    p.add_argument("repo", help="the Butler repository (butler create REPO --seed-config ...)")
    p.add_argument("files", nargs="+", help="FITS exposures")
    p.add_argument("--run", required=True, help="run collection to put them in (pipetask's -i)")
    p.add_argument("--instrument", required=True, help="instrument name of the data IDs "
                   "(recorded if new)")
    p.add_argument("--data-id", action="append", metavar="exposure=N,detector=M",
                   help="the data ID of each file, once per file in order (default: the "
                   "headers' EXPOSURE/EXPID/EXPNUM and DETECTOR/CCDNUM/DETNUM)")
    # None: put_exposures' default, the pipeline's input (the middleware is imported
    # only when the command runs, so the parser cannot read it from there)
    p.add_argument("--dataset-type", help="dataset type, registered if missing (default: the "
                   "pipeline's input, post_isr_image)")
    p.add_argument("--filter", help="physical filter recorded for new exposures (default: "
                   "the FILTER keyword, else 'unknown')")
    add_common_options(p, "json", "quiet")
    p.set_defaults(func=cmd_butler_put)
    return p
