"""pcrelight: relight a 3D object by a scanned LDR point cloud.

Conventions (DESIGN.md, once for all): right-handed, +Y up, metres, radians;
colours are linear Rec.709/sRGB-primaries RGB, float32; luminance is CIE Y.
"""

__version__ = "0.1.0"
