"""Secondary dynamics (Zoss et al. 2020): features, removal network F, synthesis network H."""

from .._areas import import_modules

import_modules(__name__, ["networks", "removal", "synthesis", "descriptors", "evaluate", "files", "take_files",
                          "takes"])
