"""``python -m tamrm``: the server's own command line (``serve``, ``healthcheck``, ``key``...).

The wheel installs the server binary itself as the ``tamrm`` command; this runs the same
binary (or ``TAMRM_BIN``), replacing the Python process, so that its flags, output, exit
codes and signal handling are the binary's own.
"""

from __future__ import annotations

import os
import sys

from tamrm._server import ServerStartError, find_binary


def main() -> None:
    """Replace this process with ``tamrm`` and the arguments given."""
    try:
        binary = find_binary()
    except ServerStartError as e:
        print(f"tamrm: {e}", file=sys.stderr)
        raise SystemExit(127) from None
    os.execv(binary, ["tamrm", *sys.argv[1:]])


if __name__ == "__main__":
    main()
