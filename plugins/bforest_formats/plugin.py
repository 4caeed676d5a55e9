"""Entry point of the ``bforest_formats`` plugin: the formats of other QSM tools, the native CSV,
meshes and synthetic scans (TreeQSM's own formats are the ``bforest_treeqsm`` plugin's).

Readers (``bf.read_qsm``; detected from content, or by ``reader=<name>``):

========================  =====================================================================
``simpleforest-csv``      SimpleForest CSV (0-based ids, end points)
``archi-csv``             aRchi CSV (1-based ids, end points)
``bforest-csv``           the native CSV written by the ``bforest-csv`` writer
========================  =====================================================================

Writers (``bf.write_tree``; by suffix or ``format=<name>``): ``bforest-csv`` (.csv + .json),
``ply`` (.ply), ``obj`` (.obj), the other tools' CSV layouts ``simpleforest-csv`` and
``archi-csv`` (by name), and the synthetic laser scans ``las`` (.las, .laz) and ``xyz`` (.xyz).
"""

from bforest_core.hookspecs import hookimpl

from .csv_readers import ArchiCSVReader, NativeCSVReader, SimpleForestCSVReader
from .foreign_csv import ArchiCSVWriter, SimpleForestCSVWriter
from .scan import LASWriter, XYZWriter
from .writers import CSVWriter, OBJWriter, PLYWriter

READERS = [SimpleForestCSVReader, ArchiCSVReader, NativeCSVReader]
WRITERS = [CSVWriter, PLYWriter, OBJWriter, LASWriter, XYZWriter, SimpleForestCSVWriter, ArchiCSVWriter]

__all__ = ["READERS", "WRITERS", "bforest_components"]


@hookimpl
def bforest_components():
    return READERS + WRITERS
