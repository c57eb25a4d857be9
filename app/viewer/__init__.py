"""The 3D view of an inspection: viser behind a websocket bridge on the app's own port.

Layout
------
Each inspection that a browser looks at gets its own :class:`viser.ViserServer`,
bound to loopback on an ephemeral port. FastAPI serves viser's bundled client
page at ``/viewer/{inspection_id}/`` and bridges the websocket the page opens
(``/viewer/{inspection_id}``) to that inspection's viser server. Which plate a
browser sees is therefore fixed by the bridge path, not by the page's query
string (which viser never receives, viser issue #365): every client of an
inspection's server is, by construction, a client of that inspection. No
private viser attribute is used.

Inside a server every browser gets its own scene and GUI (``on_client_connect``):
the measured surface coloured by signed deviation, the registered CAD target,
a layout toggle (side by side / overlaid with the target translucent) and a
colour legend in mm. A server with no client left is stopped after
``idle_s`` seconds, and at most ``max_servers`` run at once (an idle one makes
room; when all have browsers the page says so).

Room for the operator: a client without a valid dashboard session that is not on
loopback (anonymous; reads are open on the cell network) holds at most
``max_sockets_per_client`` viewer websockets per address, and starts a server only
while fewer than ``max_servers - reserved_servers`` servers have a browser. The
operator (a dashboard session, or the cell's own screen on loopback) may use every
server, so a few anonymous clients cannot take the 3D view from the cell.

Display frame: metres, origin at the centre of the measured surface's bounding
box, axes ``(x, -y, -z)`` of the left camera frame, so the side of the plate that
faces the cameras looks up (+z, viser's up direction).

Sharing is off: the share button is hidden and the server refuses share
requests (the cell network is closed).
"""

from app.viewer.bridge import (
    CLOSE_NOT_FOUND,
    CLOSE_TRY_AGAIN_LATER,
    VISER_SUBPROTOCOL,
    attach,
    router,
    viewer_bridge,
    viewer_page,
)
from app.viewer.meshes import (
    SCALE_TOLERANCES,
    PlateMeshes,
    decimate_mesh,
    deviation_colours,
    legend_html,
    load_plate_meshes,
)
from app.viewer.pool import PlateViewer, ViewerBusyError
from pipeline.artifacts.ply import DEVIATION_PROPERTIES, read_surface_ply

__all__ = [
    "CLOSE_NOT_FOUND",
    "CLOSE_TRY_AGAIN_LATER",
    "DEVIATION_PROPERTIES",
    "SCALE_TOLERANCES",
    "VISER_SUBPROTOCOL",
    "PlateMeshes",
    "PlateViewer",
    "ViewerBusyError",
    "attach",
    "decimate_mesh",
    "deviation_colours",
    "legend_html",
    "load_plate_meshes",
    "read_surface_ply",
    "router",
    "viewer_bridge",
    "viewer_page",
]
