#!/usr/bin/env bash
# Create .venv-openpi with openpi's published client (openpi-client 0.1.2), which pins numpy<2 and so cannot
# share .venv. tests/test_serving.py runs its WebsocketClientPolicy against pivla's server from this venv.
# typing_extensions is imported by the client but missing from its declared dependencies.
# Idempotent: an existing venv that already imports the client is left as it is.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${OPENPI_VENV:-.venv-openpi}"
PY="${PYTHON:-python3}"
if [[ -x "$VENV/bin/python" ]] && "$VENV/bin/python" -c "import openpi_client.websocket_client_policy" 2>/dev/null; then
  exit 0
fi
[[ -x "$VENV/bin/python" ]] || "$PY" -m venv "$VENV"
"$VENV/bin/pip" install -q "openpi-client==0.1.2" typing_extensions
"$VENV/bin/python" -c "import openpi_client.websocket_client_policy"
echo "setup-openpi-client: $VENV ready"
