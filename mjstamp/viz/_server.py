"""meshcat server process: `python -m mjstamp.viz._server [PORT] [PARENT_PID]`.

meshcat's own launcher cannot be given the web port, and prints to our
stdout; this one takes the port, reports `zmq_url=...` and `web_url=...` (or
one `error=...` line and exit status 1 where it cannot start), listens on
127.0.0.1 only, and quits when the process that started it is gone, so no
orphan server keeps the port.
"""

from __future__ import annotations

import os
import sys


def main(argv: list[str]) -> int:
    """Runs the server until interrupted or orphaned."""
    port = int(argv[0]) if argv and argv[0] != "-" else None
    parent = int(argv[1]) if len(argv) > 1 else None
    try:
        import tornado.ioloop
        from meshcat.servers.zmqserver import ZMQWebSocketBridge

        class LocalBridge(ZMQWebSocketBridge):
            """The bridge, its web server bound to 127.0.0.1 (meshcat's listens on all)."""

            def make_app(self):
                app = super().make_app()
                listen = app.listen
                app.listen = lambda port, **kw: listen(port, address=self.host, **kw)
                return app

        bridge = LocalBridge(port=port)
    except Exception as e:  # noqa: BLE001 - any failure to start is reported as one line
        reason = getattr(e, "strerror", None) or str(e) or type(e).__name__
        print(f"error={reason}", flush=True)
        return 1
    print(f"zmq_url={bridge.zmq_url}", flush=True)
    print(f"web_url={bridge.web_url}", flush=True)
    sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - our starter stops reading the pipe now
    if parent is not None:
        def check_parent():
            if os.getppid() != parent:  # re-parented: whoever started us has exited
                bridge.ioloop.stop()

        tornado.ioloop.PeriodicCallback(check_parent, 1000).start()
    try:
        bridge.run()
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
