"""numba checks a cached kernel against its own source file only: ``compile_cache.drop_if_older`` drops the
cached compilation of a kernel whose inlined helpers (another file) changed after it was cached."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap


def test_a_kernel_is_recompiled_when_a_helper_in_another_file_changes(tmp_path):
    (tmp_path / "helpers.py").write_text("from numba import njit\n\n@njit(cache=True)\ndef h(x):\n    return x + 1\n")
    (tmp_path / "main_kernel.py").write_text(textwrap.dedent("""
        import helpers
        from numba import njit
        from localization.core.compile_cache import drop_if_older

        @njit(cache=True)
        def k(x):
            return helpers.h(x)

        DROPPED = drop_if_older(k, helpers.__file__)
        print(k(1), DROPPED)
    """))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), *sys.path]))

    def run():
        return subprocess.run([sys.executable, str(tmp_path / "main_kernel.py")], capture_output=True, text=True,
                              env=env, cwd=tmp_path, check=True).stdout.split()

    assert run() == ["2", "False"]  # compiled and cached
    assert run() == ["2", "False"]  # loaded from the cache
    helpers = tmp_path / "helpers.py"
    helpers.write_text(helpers.read_text().replace("x + 1", "x + 5"))
    for index in (tmp_path / "__pycache__").glob("main_kernel.k-*.nbi"):  # cached before the helper changed
        earlier = os.path.getmtime(helpers) - 10.0
        os.utime(index, (earlier, earlier))
    assert run() == ["6", "True"]  # without dropping it numba would have loaded k's stale machine code: 2
    assert run() == ["6", "False"]
