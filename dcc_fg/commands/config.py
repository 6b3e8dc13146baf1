"""``dcc-fg config --print calibrate|validate|vio``: the options of a command as a YAML file.

Without ``--from``, the defaults; with ``--from OUT/summary.json``, the options an earlier run used
(so ``dcc-fg vio BAG ... --config that.yaml`` reproduces it). The file loads with ``--config``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from dcc_fg.commands import common
from dcc_fg.commands.calibrate import CalibrateConfig, ValidateConfig
from dcc_fg.commands.vio import VioConfig, check_config, config_text_vio
from dcc_fg.io.output_set import OutputFiles
from dcc_fg.util.config import dump_yaml, load_yaml_config
from dcc_fg.util.provenance import package_version

CONFIGS: dict[str, type] = {"calibrate": CalibrateConfig, "validate": ValidateConfig, "vio": VioConfig}


CONFIG_SUMMARY = "print a command's options as a YAML file for --config"
CONFIG_DESCRIPTION = (
    "Writes every option of a command with its default (or, with --from, the options an earlier "
    "run recorded in its summary.json) as YAML that the command reads back with --config FILE."
)


def config_text(command: str, source: Path | None = None) -> str:
    """YAML text of the defaults of ``command`` (or of the run recorded in ``source``)."""
    config = load_yaml_config(source, CONFIGS[command], command) if source else CONFIGS[command]()
    origin = f"the options of the run in {source}" if source else "the defaults"
    header = (
        f"dcc-fg {command} options ({origin}; dcc-fg {package_version()}).\n"
        f"Use: dcc-fg {command} ... --config THIS.yaml  (flags given on the command line override it).\n"
        "Units: metres, radians, seconds unless a name says otherwise (_ms, _deg, pixel_)."
    )
    if isinstance(config, VioConfig):
        check_config(config, str(source or "defaults"))
        header += "\nfrontend: overrides of FrontendConfig (defaults scaled to the image size); e.g. max_features: 200"
        return dump_yaml(config_text_vio(config), command, header)
    return dump_yaml(config, command, header)


def config_command(args: argparse.Namespace) -> int:
    outputs = OutputFiles({"--out": args.out}, {"--from": args.source}) if args.out else None
    if args.out and Path(args.out).exists() and not args.force:
        raise ValueError(f"{args.out}: exists; choose another name or pass --force")
    text = config_text(args.print, Path(args.source) if args.source else None)
    if outputs is not None:
        with outputs:
            outputs["--out"].write_text(text, encoding="utf-8")
        print(f"wrote {args.out}")
    else:
        print(text, end="")
    return 0


def add_parser(sub: Any, parent: argparse.ArgumentParser) -> None:
    c = common.add_command(sub, "config", parent, CONFIG_SUMMARY, CONFIG_DESCRIPTION, config_command)
    c.add_argument("--print", required=True, choices=sorted(CONFIGS), help="the command whose options to print")
    c.add_argument("--from", dest="source", metavar="SUMMARY_JSON", help="take the options of an earlier run")
    c.add_argument("--out", help="write to this file instead of standard output (not a folder, not the --from file)")
    c.add_argument("--force", action="store_true", help="replace --out if it exists")
