"""The ego vehicle's own lidar returns: moved to :mod:`evgrid.preprocess` (what is removed from
a frame before any ISM); these names stay importable from here.

Each name is imported ``as`` itself (an explicit re-export, which a star import also gives),
so this module repeats no list of :mod:`evgrid.preprocess`'s ``__all__``.
"""

from evgrid.preprocess import NUSCENES_BODY as NUSCENES_BODY
from evgrid.preprocess import SELF_RETURN_MODES as SELF_RETURN_MODES
from evgrid.preprocess import BodyBox as BodyBox
from evgrid.preprocess import SelfReturnFilter as SelfReturnFilter
from evgrid.preprocess import SelfReturnParams as SelfReturnParams
from evgrid.preprocess import parse_body_box as parse_body_box
