"""`rigctl init KIND [-o FILE] [--force]`: a commented rig file for real hardware.

Each rig kind brings its template (`RigKind.template`; rigctl's own three keep theirs in
`template.toml` in each kind's package, package data): the seed papers' hardware, with comments saying
what a lab must change; each loads with `load_rig` as it is, so `rigctl doctor` can check it
before anything is edited. The kinds offered are the registry's.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rigctl.core.errors import EXIT_OK, ConfigError
from rigctl.core.registry import entry_point_names, rig_kind


def template(kind: str) -> str:
    """The commented rig file of a rig kind, as text (ConfigError for a kind without one)."""
    make = rig_kind(kind).template
    if make is None:
        raise ConfigError(f"rig kind {kind!r} has no rig file template for `rigctl init`")
    return make()


def _cmd_init(args: argparse.Namespace) -> int:
    text = template(args.kind)
    if args.output is None:
        sys.stdout.write(text)
        return EXIT_OK
    out = Path(args.output)
    if out.exists() and not args.force:
        raise ConfigError(f"{out} exists: not overwritten (--force replaces it)")
    try:
        out.write_text(text)
    except OSError as err:
        raise ConfigError(f"cannot write {out}: {err.strerror or err}") from None
    print(f"wrote {out}: edit the lines marked CHANGE:, then `rigctl doctor --rig {out}`",
          file=sys.stderr)
    return EXIT_OK


def register_init(sub) -> None:
    p = sub.add_parser(
        "init", help="write a commented rig file for a real rig (the seed papers' hardware)",
        description="Write a rig file for real hardware: every device with its address, the "
        "settings of the seed papers' rig, and comments saying what to change. Check it with "
        "`rigctl doctor --rig FILE` (nothing is energised). Refuses to overwrite a file.")
    p.add_argument("kind", choices=entry_point_names(), help="rig kind (the installed ones)")
    p.add_argument("-o", "--output", help="write the rig file here (default: print it)")
    p.add_argument("--force", action="store_true", help="overwrite an existing file")
    p.set_defaults(func=_cmd_init)
