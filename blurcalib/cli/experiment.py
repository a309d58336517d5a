"""``blurcalib experiment``: one of the paper's experiments, its options handed on."""

from __future__ import annotations

import argparse

from blurcalib.cli.common import plain


def cmd_experiment(args: argparse.Namespace) -> int:
    """Reproduce one of the paper's experiments on simulated data (docs/experiments.md); the
    options of each are in blurcalib experiment NAME --help."""
    from blurcalib.paper import alignment, generic, patterns, psf_quality, threshold_sweep

    runners = {"patterns": patterns.main, "alignment": alignment.main,
               "psf-quality": psf_quality.main, "threshold-sweep": threshold_sweep.main,
               "generic": generic.main}
    return runners[args.name](args.rest)


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Register ``experiment``."""
    p = sub.add_parser("experiment", help="reproduce one of the paper's experiments",
                       description=plain(cmd_experiment.__doc__))
    p.add_argument("name", choices=["patterns", "alignment", "psf-quality", "threshold-sweep", "generic"],
                   metavar="NAME",
                   help="patterns: star vs checkerboard PSF recovery (fig:exp2_test); "
                        "alignment: global alignment verification (tab:exp4, fig:exp41, fig:exp42); "
                        "psf-quality: PSF field and quality scatter plots (fig:exp_real1, "
                        "fig:exp_real2); threshold-sweep: error against tau_L (fig:exp_real3); "
                        "generic: generic camera from sharp and blurry frames vs the truth")
    p.add_argument("rest", nargs=argparse.REMAINDER, metavar="OPTIONS",
                   help="options of the experiment (see blurcalib experiment NAME --help)")
    p.set_defaults(func=cmd_experiment)
