"""The 13 mouth-shape parameters and the six mouth bases every spoken mouth is interpolated from.

Each parameter is a displacement of one lip control point along one axis, in millimetres on the
built-in face (the face rig turns a parameter vector into feature-point displacements). Signs:
vertical is up, depth is forward (out of the face), horizontal is outward from the face's midline.
"""

import numpy as np

MOUTH_PARAMETERS = (
    "upper_lip_top_vertical",
    "upper_lip_top_depth",
    "upper_lip_bottom_vertical",
    "upper_lip_bottom_depth",
    "lower_lip_top_vertical",
    "lower_lip_top_depth",
    "lower_lip_bottom_vertical",
    "lower_lip_bottom_depth",
    "jaw_vertical",
    "corner_vertical",
    "corner_horizontal",
    "corner_depth",
    "lip_width",
)
NUM_MOUTH_PARAMETERS = len(MOUTH_PARAMETERS)

# Japanese vowels plus the closed mouth; /a/ opens the jaw most, /i/ spreads the corners, /u/ and /o/
# round and push the lips forward, /e/ sits between /a/ and /i/.
VOWELS = ("a", "i", "u", "e", "o", "closed")
_BASES = {
    #         ult_v ult_d ulb_v ulb_d llt_v llt_d llb_v llb_d  jaw  cor_v cor_h cor_d width
    "a":      (1.0, 0.0, 3.0, 0.0, -11.0, 0.0, -11.0, -1.0, -12.0, -1.0, 1.0, 0.0, 1.0),
    "i":      (0.5, -1.0, 1.5, -1.0, -3.0, -1.0, -2.5, -1.0, -3.0, 1.5, 8.0, -1.0, 4.0),
    "u":      (0.0, 5.0, 1.0, 6.0, -2.5, 6.0, -1.5, 4.0, -4.0, 0.0, -8.0, 3.0, -5.0),
    "e":      (0.5, 0.0, 2.0, 0.0, -7.0, 0.0, -6.5, -0.5, -7.0, 0.0, 5.0, 0.0, 2.0),
    "o":      (0.5, 3.0, 3.0, 4.0, -8.0, 4.0, -7.5, 2.0, -9.0, -0.5, -5.0, 2.0, -3.0),
    "closed": (0.0,) * NUM_MOUTH_PARAMETERS,
}
VOWEL_SHAPES = np.array([_BASES[v] for v in VOWELS], np.float64)  # (6, 13) millimetres


def vowel_shape(name):
    """The 13 mouth parameters [mm] of one base ('a', 'i', 'u', 'e', 'o' or 'closed')."""
    if name not in _BASES:
        raise KeyError(f"unknown mouth base '{name}' (expected one of {', '.join(VOWELS)})")
    return VOWEL_SHAPES[VOWELS.index(name)].copy()


def mouth_from_weights(weights):
    """Interpolate the bases: weights (..., 6) in VOWELS order -> parameters (..., 13) [mm]."""
    return np.asarray(weights, np.float64) @ VOWEL_SHAPES


def nearest_vowel(params):
    """Index into VOWELS of the base closest (Euclidean, mm) to each parameter vector (..., 13)."""
    params = np.asarray(params, np.float64)
    d = np.linalg.norm(params[..., None, :] - VOWEL_SHAPES, axis=-1)
    return np.argmin(d, axis=-1)
