"""``pivla serve``: a policy behind a WebSocket, for a robot or evaluation on another machine."""

from __future__ import annotations

from pivla.serving.server import ServeConfig


def serve(cfg: ServeConfig) -> int:
    """openpi's wire protocol: openpi's WebsocketClientPolicy and pivla's RemotePolicy (pivla eval --policy
    ws://HOST:PORT, pivla robot run --policy ws://HOST:PORT) both work against it. Binds loopback unless told
    otherwise; any other address needs --api-key-file. GET /healthz answers 200 for load balancers."""
    from pivla.serving.server import serve as run

    try:
        run(cfg)
    except ValueError as e:
        raise SystemExit(f"pivla serve: {e}") from e
    return 0
