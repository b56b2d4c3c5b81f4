"""Old import path of ``omniscs.scs.behavior.render_consistency`` (L_app), kept only for omniscs/bench/behavior.py;
delete once it imports the new module ("appearance" now names appearance-level SCS alone)."""
from omniscs.scs.behavior.render_consistency import masked_psnr, variant_ego_poses

__all__ = ["masked_psnr", "variant_ego_poses"]
