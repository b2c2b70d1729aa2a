"""The README's Python snippets run as written (documentation that cannot rot)."""

import pathlib
import re

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_blocks_run():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert len(blocks) >= 2
    for block in blocks:
        namespace: dict = {}
        exec(compile(block, str(README), "exec"), namespace)  # raises on any error
    # the last block's gradient w.r.t. the 6 log-Cholesky parameters is finite
    import numpy as np

    assert np.all(np.isfinite(np.asarray(namespace["g"]))) and namespace["g"].shape == (6,)
