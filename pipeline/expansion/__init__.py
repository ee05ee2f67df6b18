"""The HDR expansion of the LDR cloud (§4): expose-match, render-cubemaps, patchmatch, reproject, poisson, and what they share (inverse tone mapping, point splats, photo sets, photo registration)."""
