"""numba's compiler where it is installed (the `fast` extra) and not switched off by `YOTO_NO_NUMBA=1`.

`ENABLED` says whether `jit` compiles. Without numba `jit` returns the function unchanged: callers test `ENABLED`
(or their module's kernels) and take their numpy paths, so the plain-Python loops are never run. Compiled code is
cached on disk (`cache=True`: next to the module, or under NUMBA_CACHE_DIR / the user's cache folder where the
package is read-only), so only the first process after an install pays the compile; `nogil`: a helper thread may
run beside; no fastmath: the loops keep IEEE arithmetic in the order written.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

jit: Callable[[Any], Any] = lambda function: function  # noqa: E731 (replaced by numba's njit below)
ENABLED = False
if os.environ.get("YOTO_NO_NUMBA", "") in ("", "0"):
    try:
        import numba

        jit = numba.njit(cache=True, nogil=True)  # module-level functions: the on-disk cache finds them again
        ENABLED = True
    except ImportError:  # the numpy paths
        pass
