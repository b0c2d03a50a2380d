"""``tissuecast config show [FILE|STORE]``: print the effective configuration as TOML."""

from __future__ import annotations

from ..config import config_to_toml


def register(sub) -> None:
    p = sub.add_parser("config", help="show the effective configuration")
    csub = p.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    show = csub.add_parser("show", help="print the effective config (defaults = the paper's values)")
    show.add_argument("file", nargs="?", help="TOML config file or a packaged preset (embedded, paper, quick); omitted = "
                      "defaults; "
                      "or a data-set store directory: the config it was made with")
    show.add_argument("--no-comments", action="store_true", help="omit the explanatory comments (a changed value's "
                      "comment starts 'changed (default ...)')")
    show.add_argument("--changed", action="store_true", help="only the values that differ from the defaults (what a "
                      "preset or file changes; reads back to the same config)")
    show.set_defaults(func=run)


def run(args) -> int:
    from ..app.pipeline import resolve_source

    cfg, _ = resolve_source(args.file)
    print(config_to_toml(cfg, comments=not args.no_comments, changed_only=args.changed), end="")
    return 0
