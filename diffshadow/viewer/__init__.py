"""The interactive viewer (`diffshadow view`): move the light through a finished scene in a browser and see
the cached shadow. `scene` holds what is shown (no browser needed); `app` serves it with viser."""

from typing import Any

from diffshadow.viewer.scene import ViewerError, ViewerScene, azimuth_elevation, direction


def serve(**kwargs: Any) -> None:
    """`app.serve`, imported when called (viser is needed only to serve)."""
    from diffshadow.viewer.app import serve as _serve

    _serve(**kwargs)


__all__ = ["ViewerError", "ViewerScene", "azimuth_elevation", "direction", "serve"]
