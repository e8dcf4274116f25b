"""A node process that says whether it should show progress as on a terminal, then ends."""

import sys

from msgs.progress import on_terminal

if __name__ == "__main__":
    print(f"progress on a terminal: {on_terminal(sys.stdout)}", flush=True)
