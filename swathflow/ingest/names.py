"""Image ids are names: they name files (``<id>.tif``) and STAC items, never paths."""
from __future__ import annotations

import re

#: image ids that name one of the run's own products (the mosaic's STAC item)
RESERVED_IDS = ("mosaic",)
#: endings of an image's extra products (``<id>.glt.tif``): no id may end so
PRODUCT_ENDINGS = (".glt", ".igm")


def id_problem(iid) -> str:
    """Why ``iid`` cannot be an image id (empty: it can). Ids name files (``<id>.tif``)
    and STAC items: a plain name, never a path."""
    if not isinstance(iid, str):
        return f"must be a string, got {iid!r}"
    if not re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9_.\-]{0,127}", iid) or ".." in iid:
        return (f"{iid!r} is not a plain name (path separators, '..', spaces and other "
                f"characters would place its products outside the output folder or make "
                f"them unreadable)")
    if iid.lower() in RESERVED_IDS:
        return f"{iid!r} is the name of one of the run's own products (the mosaic)"
    if iid.lower().endswith(PRODUCT_ENDINGS + (".tif", ".tiff", ".json")):
        return f"{iid!r} ends like the file of another image's product"
    return ""
