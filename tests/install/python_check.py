# What `import chimera` must do right after `meson install` (tests/install):
# load the installed package and extension (not the build tree's), create a
# table from the test .svar through the installed libchimera, and read it.
#   python3 python_check.py FILE.svar NAME EXPECTED-PACKAGE-FOLDER-PREFIX
import sys

import chimera

svar, name, where = sys.argv[1:4]
assert chimera.__file__.startswith(where), "chimera imported from %s, not under %s" % (chimera.__file__, where)
assert chimera._core.__file__.startswith(where), chimera._core.__file__
table = chimera.Table.create(name, svar)
gain = table.info("GAIN")
print("python: %s %s, GAIN %s in [%g, %g], Q_REF %s" % (
    table.segment, len(table), gain.type, gain.min[0], gain.max[0], table.read("Q_REF").tolist()))
