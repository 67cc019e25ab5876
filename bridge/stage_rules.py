"""The rules the cached stages are built by, one version string each.

Each string is part of its stage's key (`bodies`), so a stage built under other rules is never
read for this one: it is rebuilt. Bump a string when what its stage holds, or how it is
computed, changes. `prepared_rules` is what a Prepare depends on; `staleness` records it with
what Prepare read, so a file prepared by a version with other rules shows as needing Prepare
again (in the panel too) before any operator tries to rebuild its stages.
"""

# How the energy cubature is trained (what its key leaves out: Young's modulus, density).
ENERGY_RULES = "energy-3: trained at Young's modulus 1 Pa, in the modes at 1 kg/m^3"

# The automatic basis and cubature sizing and training range (solver.reduced).
REDUCED_RULES = "reduced-2: O(m^2) basis, cubature 1.25 rB, training to 180 deg"

# The pin rule (solver.embed.pin_surface); part of a pinned body's modes key.
PIN_RULES = "surface pins 2: faces clamp by their tet-surface facets"

# What the modes stage holds.
MODES_RULES = "modes 3: at Young's modulus 1 Pa and density 1 kg/m^3, moved to the body's"

# The painted stiffness rule (solver.preparation.stiffness_scale); part of a painted body's
# modes key.
STIFFNESS_RULES = "painted stiffness 1: geometric in the mean of the tet's carried node weights"


def prepared_rules():
    """The rules of the stages Prepare builds (modes, pins, painted stiffness, reduced), as one
    text. Read at call time, so a test can change one rule."""
    return repr((MODES_RULES, PIN_RULES, STIFFNESS_RULES, REDUCED_RULES))
