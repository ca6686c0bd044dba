"""``spot config``: show resolved run configs and the valid keys. (Named config_cmd so that it is
not mistaken for ``spot.config``, the library module it reads.)"""

from __future__ import annotations

import argparse
from typing import Any

from spot.cli.common import subcommand


def add(sub: Any) -> None:
    """The config: show, keys commands."""
    cfg = sub.add_parser("config", help="show resolved run configs and valid keys").add_subparsers(
        dest="sub", required=True, metavar="SUB"
    )
    d = subcommand(cfg, "show", "print the fully resolved config", "spot config show configs/quickstart.yaml method=pt")
    d.add_argument("config", nargs="?", help="YAML run config")
    d.add_argument("overrides", nargs="*", help="a.b=value overrides")
    d.set_defaults(fn=_config_show)
    d = subcommand(cfg, "keys", "every config key with type, help and valid values", "spot config keys | grep '^iql'")
    d.set_defaults(fn=_config_keys)


def _config_show(args: argparse.Namespace) -> None:
    from spot import config

    print(config.to_yaml(config.load(args.config, args.overrides)), end="")


def _config_keys(args: argparse.Namespace) -> None:
    from spot import config

    for key in config.valid_keys():
        tp, meta = config.field_info(key)
        extra = ""
        if meta.get("choices"):
            extra = f" one of {list(meta['choices'])}"
        elif meta.get("range"):
            extra = f" in [{meta['range'][0]}, {meta['range'][1]}]"
        print(f"{key:26s} {getattr(tp, '__name__', str(tp)):8s} {meta.get('help', '')}{extra}")
