"""The shape of the package, as the renovation reports it: lines per module, functions over
100 lines, lines over 100 columns, and the command line's size (lines of the modules that
declare commands or options, and the options they declare).

    python benchmarks/code_shape.py [SRC]      # default: src/evgrid of this checkout
"""

from __future__ import annotations

import ast
import json
import re
import sys
from pathlib import Path


def shape(src: Path) -> dict:
    modules, long_functions, wide = {}, [], 0
    cli_lines, cli_options, cli_modules = 0, 0, []
    for path in sorted(src.rglob("*.py")):
        text = path.read_text()
        lines = text.splitlines()
        rel = str(path.relative_to(src.parent))
        modules[rel] = len(lines)
        wide += sum(len(line) > 100 for line in lines)
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > 100:
                    long_functions.append((f"{rel}:{node.name}", n))
        # a module that declares commands or options: typer/click decorators or option calls
        options = len(re.findall(r"typer\.Option\(|click\.option\(|add_argument\(", text))
        if options or re.search(r"@\w+\.command\(|@_command\(", text):
            cli_modules.append(rel)
            cli_lines += len(lines)
            cli_options += options
    return {
        "modules": len(modules),
        "lines": sum(modules.values()),
        "largest": sorted(modules.items(), key=lambda kv: -kv[1])[:12],
        "functions_over_100_lines": sorted(long_functions, key=lambda kv: -kv[1]),
        "lines_over_100_columns": wide,
        "cli": {"modules": cli_modules, "lines": cli_lines, "options": cli_options},
    }


if __name__ == "__main__":
    root = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parents[1] / "src" / "evgrid"
    print(json.dumps(shape(root), indent=1))
