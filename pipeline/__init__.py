"""pcrelight: relight a 3D object by a scanned LDR point cloud.

Conventions (DESIGN.md, once for all): right-handed, +Y up, metres, radians;
colours are linear Rec.709/sRGB-primaries RGB, float32; luminance is CIE Y.
"""

import os as _os

__version__ = "0.1.0"

# numba's parallel loops run on GNU OpenMP here (numba.threading_layer() == "omp"). Its default wait policy spins
# each worker after a parallel region: on a busy 2-core machine that was ~0.1 CPU s (0.2 s wall) per call of a small
# kernel (radix_argsort of 2 178 keys: 0.000 s passive), and the spinning threads took the cores from llvmpipe's
# walks that follow the object's surfel BSH (bench/README.md 'relight's fixed costs'). Set before libgomp loads (at
# the first parallel call); a value the user set wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
