"""Serving a policy over the network with openpi's WebSocket protocol, and a client that is a ``ChunkPolicy``.

- :mod:`pivla.serving.server`: ``serve(ServeConfig(policy=RUN))`` (needs PyTorch: it runs the model);
- :mod:`pivla.serving.client`: ``RemotePolicy(url, api_key)`` for executors, evaluation and the arm (no
  PyTorch, no MuJoCo);
- :mod:`pivla.serving.protocol`: the wire protocol, openpi's with a few named methods;
- :mod:`pivla.serving.msgpack_numpy`: arrays in msgpack as openpi encodes them, without pickle;
- :mod:`pivla.bench.serve`: loopback latency against in-process, and AURD's closed loop remote vs local.
"""

from pivla.serving.client import RemotePolicy, ServerError, ServerRefused

__all__ = ["RemotePolicy", "ServerError", "ServerRefused"]
