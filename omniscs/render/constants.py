"""Numbers that define the splatting model (gsplat's "classic" 3DGS rules), shared by every backend."""

#: A Gaussian adds nothing to a pixel where its alpha is below this (gsplat's ALPHA_THRESHOLD).
ALPHA_THRESHOLD = 1.0 / 255.0

#: Alpha is clamped to this so that 1 - alpha never reaches 0 (keeps transmittance invertible).
MAX_ALPHA = 0.999

#: A pixel stops compositing before the Gaussian that would bring its transmittance to or below this.
TRANSMITTANCE_STOP = 1e-4

#: The perspective Jacobian is evaluated with x/z, y/z clamped to the half-FOV tangent plus this
#: fraction of it (gsplat's 1.3x frustum clamp), which tames Gaussians far outside the view.
FRUSTUM_MARGIN = 0.3

#: Side of the square screen tiles the CPU backend bins Gaussians into, in pixels.
TILE_SIZE = 16

#: Largest screen radius (pixels) stored in ``radii``; keeps huge Gaussians inside int32.
MAX_RADIUS = 1 << 24
