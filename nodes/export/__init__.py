"""Writers of animation files a DCC reads: Live Link Face CSV, USD and glTF (readers are in `nodes.io`)."""

from .._areas import import_modules

import_modules(__name__, ["scene", "livelink", "usd", "gltf"])
