# What `import chimera` must do right after `meson install` (tests/install):
# load the installed package and extension (not the build tree's), create a
# table from the test .svar through the installed libchimera, and read it;
# chimera.__version__ is the one the source tree's meson.build declares.
#   python3 python_check.py FILE.svar NAME EXPECTED-PACKAGE-FOLDER-PREFIX
import os
import re
import sys

import chimera

svar, name, where = sys.argv[1:4]
assert chimera.__file__.startswith(where), "chimera imported from %s, not under %s" % (chimera.__file__, where)
assert chimera._core.__file__.startswith(where), chimera._core.__file__
with open(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "meson.build")) as f:
    version = re.search(r"project\([^)]*?version\s*:\s*'([^']+)'", f.read()).group(1)
assert chimera.__version__ == version, "chimera.__version__ %r, meson.build declares %r" % (chimera.__version__, version)
table = chimera.Table.create(name, svar)
gain = table.info("GAIN")
print("python: chimera %s, %s %s, GAIN %s in [%g, %g], Q_REF %s" % (
    chimera.__version__, table.segment, len(table), gain.type, gain.min[0], gain.max[0], table.read("Q_REF").tolist()))
