"""`rigctl view RUN [--runs DIR] [--no-browser]`: a run record in the browser's run viewer.

The viewer's routes (`rigctl.apps.console.records`) served alone, on loopback at a free port, for
the folder that holds the record (so its list shows the neighbours too), and the browser opened
at the record (`webbrowser`; `--no-browser` only prints the URL, e.g. on a machine reached over
SSH with a forwarded port). It reads the record and serves nothing else: no daemon, no rig. It
runs until Ctrl-C or SIGTERM, which end it with status 0.
"""

from __future__ import annotations

import argparse
import asyncio
import signal
import sys
from pathlib import Path

from rigctl.core.errors import EXIT_OK, ConfigError

CSP = ("default-src 'self'; img-src 'self' blob: data:; media-src 'self'; connect-src 'self'; "
       "style-src 'self'; script-src 'self'; frame-ancestors 'none'")


async def serve(run_dir: Path, host: str, port: int, opened) -> None:
    """Serve the viewer for the records beside `run_dir` until SIGINT/SIGTERM; `opened(url)` is
    called once it serves, with the record read."""
    from aiohttp import web

    from rigctl.apps.console.records import STATIC, add_record_routes
    from rigctl.apps.console.server import is_loopback_host

    def loopback_name(request) -> bool:  # a rebinding site's name is refused (as the console)
        name = (request.host or "").rsplit(":", 1)[0].strip("[]")
        return is_loopback_host(name)

    async def headers(request, response) -> None:
        response.headers["Content-Security-Policy"] = CSP
        response.headers["X-Content-Type-Options"] = "nosniff"

    app = web.Application()
    records = add_record_routes(app, run_dir.parent, loopback_name)
    app.router.add_static("/static/", STATIC, show_index=False)
    app.on_response_prepare.append(headers)
    runner = web.AppRunner(app, access_log=None, handle_signals=False)
    await runner.setup()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        site = web.TCPSite(runner, host, port)
        try:
            await site.start()
        except OSError as err:
            raise ConfigError(f"cannot serve the viewer on {host}:{port}: {err.strerror or err}"
                              ) from None
        bound = site._server.sockets[0].getsockname()[1] if site._server is not None else port
        try:  # read now (and the readers' imports, ~1 s), not when the page first asks
            await loop.run_in_executor(None, records.document, run_dir)
        except Exception as err:  # the page says it too, when it asks
            print(f"warning: {run_dir.name} cannot be read ({err})", file=sys.stderr)
        shown = f"[{host}]" if ":" in host else host
        opened(f"http://{shown}:{bound}/viewer?run={run_dir.name}")
        await stop.wait()
    finally:
        await runner.cleanup()


def _cmd_view(args: argparse.Namespace) -> int:
    from rigctl.apps.console.server import is_loopback_host, parse_address
    from rigctl.apps.report import find_run
    from rigctl.core.extras import need

    need("aiohttp", "rigctl view")
    run_dir = find_run(args.run, args.runs).resolve()
    host, port = parse_address(args.address)
    if not is_loopback_host(host):
        raise ConfigError(f"--address {args.address}: the viewer serves on loopback only "
                          "(forward the port to reach it from elsewhere)")

    def opened(url: str) -> None:
        print(url, flush=True)
        print("the run viewer serves here; Ctrl-C ends it", file=sys.stderr, flush=True)
        if not args.no_browser:
            import webbrowser

            if not webbrowser.open(url):
                print("no browser could be opened: open the URL above", file=sys.stderr)

    asyncio.run(serve(run_dir, host, port, opened))
    print("viewer stopped", file=sys.stderr)
    return EXIT_OK


def register_view(sub) -> None:
    p = sub.add_parser(
        "view", help="open a run record in the browser: video, overlays, channels, events",
        description="Serve the run viewer for a run record on loopback (a free port) and open it "
        "in the browser: a timeline to scrub or play at 0.25-8x, the video frame of that instant "
        "with the plan and the tracked positions over it (the scene drawn from the tracked "
        "positions for a record without video; the arms for the dual-EPM rig), the channels and "
        "the events. Ctrl-C ends it.")
    p.add_argument("run", help="run record folder, a run id inside --runs (or its start), or "
                   "`latest`")
    p.add_argument("--runs", default="runs", help="run records folder (default ./runs)")
    p.add_argument("--address", default="127.0.0.1:0",
                   help="loopback address to serve on (default 127.0.0.1 at a free port)")
    p.add_argument("--no-browser", action="store_true",
                   help="print the URL only, do not open a browser")
    p.set_defaults(func=_cmd_view)
