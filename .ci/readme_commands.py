"""Print the two commands of README.md's quick start (install + demo, install + tests).

.ci/run executes exactly these lines, so README and CI cannot drift apart. The commands are the
first two lines of the first ```bash block after the "## Quick start" heading.
"""

import pathlib
import sys

text = pathlib.Path(__file__).resolve().parent.parent.joinpath("README.md").read_text()
section = text.split("## Quick start", 1)[1]
block = section.split("```bash", 1)[1].split("```", 1)[0]
lines = [ln.strip() for ln in block.strip().splitlines() if ln.strip() and not ln.startswith("#")]
if len(lines) != 2:
    sys.exit(f"README quick start must hold exactly two commands, found {len(lines)}")
print("\n".join(lines))
