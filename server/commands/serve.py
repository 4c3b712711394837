"""`xyzcyl serve`: run the HTTP service with uvicorn (and, with ``--grpc-port``, the gRPC SensorsimService beside
it: docs/simulators.md). Every Settings field is a flag (``--store``, ``--max-body-bytes``, ``--api-keys a,b``,
``--grpc-port 50051`` ...) over its ``XYZCYL_*`` environment variable; docs/api.md."""

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
            if err["loc"]:
                print(f"xyzcyl serve: {_flag(str(err['loc'][0]))}: {err['msg']} (got {err.get('input')!r})",
                      file=sys.stderr)
            else:                       # a check across fields: its message starts "<field>: "
                name, _, msg = str(err["msg"]).removeprefix("Value error, ").partition(": ")
                print(f"xyzcyl serve: {_flag(name)}: {msg}", file=sys.stderr)
        return 2
    if args.print_settings:
        shown = settings.model_dump(mode="json")
        shown["api_keys"] = [f"{k[:2]}...({len(k)} chars)" for k in settings.api_keys]
        shown["model"] = str(settings.model_dir().resolve())   # the folder it would load ($XYZCYL_MODEL, shipped)
        print(json.dumps(shown, indent=1))
        return 0
    import uvicorn
    from xyzcyl.runtime import compile_notice
    from xyzcyl.runtime.inference import ModelError

    from ..app import create_app

    log = _configure_logging(args.log_level)
    # numba's one-line compile notice through the service's log (the worker processes print it to stderr)
    compile_notice.install(log.info)

    try:
        app = create_app(settings)
    except ModelError as e:
        print(f"xyzcyl serve: --model: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"xyzcyl serve: --store: {e}", file=sys.stderr)
        return 2
    # server_header=False: no "server: uvicorn" header (the stack's versions are not announced)
    # loop "asyncio" with the gRPC API: grpc.aio runs on the event loop, and supports asyncio's own
    config = uvicorn.Config(app, host=settings.host, port=settings.port, log_level=args.log_level,
                            server_header=False, timeout_graceful_shutdown=30,
                            http=_protocol_class(settings.header_timeout_s),
                            loop="asyncio" if settings.grpc_port is not None else "auto")
    server = _server_class()(config)
    server.service = app.state.service
    server.run()
    return 0


def _configure_logging(level: str):
    """The service's own lines (loggers under "xyzcyl": ready, warm-up, recovered store, errors) on stderr at
    ``--log-level``, formatted as uvicorn's ("INFO:     ..."); without this only warnings and errors showed, bare.
    Returns the server's logger."""
    import logging

    root = logging.getLogger("xyzcyl")
    if not root.handlers:
        handler = logging.StreamHandler()
        try:
            from uvicorn.logging import DefaultFormatter

            handler.setFormatter(DefaultFormatter("%(levelprefix)s %(message)s", use_colors=False))
        except ImportError:  # pragma: no cover - uvicorn is a dependency of serve
            handler.setFormatter(logging.Formatter("%(levelname)s: %(message)s"))
        root.addHandler(handler)
        root.propagate = False
    root.setLevel(level.upper())
    return logging.getLogger("xyzcyl.server")


def _protocol_class(header_timeout_s: float):
    """uvicorn's h11 protocol with a deadline on each request head: a connection that has not sent a whole request
    line and headers within ``header_timeout_s`` of connecting, or of its previous answer, is closed. uvicorn has no
    such timeout (its keep-alive timer starts only after an answer and restarts with every byte), so a slow client
    (slowloris: a header byte every few seconds) could hold a connection, and a file descriptor, forever."""
    import h11
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class HeadTimeoutH11Protocol(H11Protocol):
        _head_timer = None

        def connection_made(self, transport):
            super().connection_made(transport)
            self._arm_head_timer()

        def _arm_head_timer(self) -> None:
            self._head_timer = self.loop.call_later(header_timeout_s, self._head_timed_out)

        def _disarm_head_timer(self) -> None:
            if self._head_timer is not None:
                self._head_timer.cancel()
                self._head_timer = None

        def handle_events(self) -> None:
            super().handle_events()
            if self.conn.their_state is not h11.IDLE:        # the request head is in (or the connection is ending)
                self._disarm_head_timer()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if self._head_timer is None and not self.transport.is_closing() and self.conn.their_state is h11.IDLE:
                self._arm_head_timer()                      # the next request on this connection

        def connection_lost(self, exc) -> None:
            self._disarm_head_timer()
            super().connection_lost(exc)

        def _head_timed_out(self) -> None:
            self._head_timer = None
            if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
                self.transport.close()

    return HeadTimeoutH11Protocol


def _server_class():
    import uvicorn

    class DrainingServer(uvicorn.Server):
        """On SIGTERM/SIGINT: /v2/health/ready turns 503 at once (load balancers stop sending), requests in
        flight finish (up to 30 s), then the workers stop."""

        service = None

        def handle_exit(self, sig, frame):
            import signal

            if self.service is not None:
                self.service.draining = True
            super().handle_exit(sig, frame)
            if sig == signal.SIGTERM:
                # a drained SIGTERM is a clean stop: exit 0. uvicorn re-raises the captured signal after draining,
                # which the default handler turns into death by SIGTERM (status 143 in a container).
                self._captured_signals = [s for s in self._captured_signals if s != signal.SIGTERM]

    return DrainingServer
