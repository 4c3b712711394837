"""`xyzcyl serve`: run the HTTP service with uvicorn. Every Settings field is a flag (``--store``,
``--max-body-bytes``, ``--api-keys a,b`` ...) over its ``XYZCYL_*`` environment variable; docs/api.md."""

from __future__ import annotations

import argparse
import sys


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..settings import Settings

    for name, f in Settings.model_fields.items():
        env = f"XYZCYL_{name.upper()}"
        parser.add_argument(_flag(name), dest=name, default=None, metavar=name.split("_")[-1].upper(),
                            help=f"{f.description} [env {env}]")
    parser.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"],
                        help="uvicorn log level")
    parser.add_argument("--print-settings", action="store_true", help="print the resolved settings and exit")


def run(args: argparse.Namespace) -> int:
    import json

    from pydantic import ValidationError

    from ..settings import Settings

    overrides = {k: v for k, v in vars(args).items() if k in Settings.model_fields and v is not None}
    try:
        settings = Settings(**overrides)
    except ValidationError as e:
        for err in e.errors():
            loc = err["loc"][0] if err["loc"] else "settings"
            print(f"xyzcyl serve: {_flag(str(loc))}: {err['msg']} (got {err.get('input')!r})", file=sys.stderr)
        return 2
    if args.print_settings:
        shown = settings.model_dump(mode="json")
        shown["api_keys"] = [f"{k[:2]}...({len(k)} chars)" for k in settings.api_keys]
        print(json.dumps(shown, indent=1))
        return 0
    import uvicorn
    from xyzcyl.runtime.inference import ModelError

    from ..app import create_app

    try:
        app = create_app(settings)
    except ModelError as e:
        print(f"xyzcyl serve: --model: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"xyzcyl serve: --store: {e}", file=sys.stderr)
        return 2
    # server_header=False: no "server: uvicorn" header (the stack's versions are not announced)
    config = uvicorn.Config(app, host=settings.host, port=settings.port, log_level=args.log_level,
                            server_header=False, timeout_graceful_shutdown=30)
    server = _server_class()(config)
    server.service = app.state.service
    server.run()
    return 0


def _server_class():
    import uvicorn

    class DrainingServer(uvicorn.Server):
        """On SIGTERM/SIGINT: /v2/health/ready turns 503 at once (load balancers stop sending), requests in
        flight finish (up to 30 s), then the workers stop."""

        service = None

        def handle_exit(self, sig, frame):
            if self.service is not None:
                self.service.draining = True
            super().handle_exit(sig, frame)

    return DrainingServer
