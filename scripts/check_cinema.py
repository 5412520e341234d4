"""Reads a Cinema database (Spec D) with pandas and Pillow, as a user's own tools would, and
checks the specification's rules: `data.csv` parses, `FILE` is the last column, every other
column is numeric (NaN allowed), and every row's file exists and is an image. Prints the rows,
columns and the image sizes found, one line; exits non-zero naming the first broken rule.

    python check_cinema.py DB.cdb [COLUMN ...]   # COLUMNs that must be present
"""

import os
import sys

import pandas as pd
from PIL import Image


def main():
    db = sys.argv[1]
    need = sys.argv[2:]
    table = pd.read_csv(os.path.join(db, "data.csv"))
    cols = list(table.columns)
    if cols[-1] != "FILE":
        sys.exit(f"FILE is not the last column: {cols}")
    for c in need:
        if c not in cols:
            sys.exit(f"column {c} is missing: {cols}")
    for c in cols[:-1]:
        if not pd.api.types.is_numeric_dtype(table[c]):
            sys.exit(f"column {c} is not numeric: {table[c].tolist()[:5]}")
    sizes = set()
    for f in table["FILE"]:
        path = os.path.join(db, f)
        if not os.path.isfile(path):
            sys.exit(f"{f} does not exist")
        with Image.open(path) as im:
            im.verify()
        with Image.open(path) as im:
            sizes.add(im.size)
    print(f"cinema ok: {len(table)} rows, columns {','.join(cols)}, images {sorted(sizes)}")


if __name__ == "__main__":
    main()
