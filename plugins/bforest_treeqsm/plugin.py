"""Entry point of the ``bforest_treeqsm`` plugin: QSM readers and tree writers.

Readers (``bf.read_qsm``; detected from content, or by ``reader=<name>``):

========================  =====================================================================
``treeqsm-mat``           TreeQSM 2.3/2.4 structs ``qsm``/``QSM``/``OptQSM``/``QSMs`` (MAT v5, v7.3)
``treeqsm-flat``          TreeQSM 2.0 flat variables and the older v7.3 flat layout (pines)
``cyldata-mat``           the 14-column ``CylData`` matrix in a ``.mat`` file
``treeqsm-text``          TreeQSM text: 17 columns + header, 15-column layouts, 14-column text
``simpleforest-csv``      SimpleForest CSV (0-based ids, end points)
``archi-csv``             aRchi CSV (1-based ids, end points)
``bforest-csv``           the native CSV written by the ``bforest-csv`` writer
========================  =====================================================================

Writers (``bf.write_tree``; by suffix or ``format=<name>``): ``treeqsm-text`` (.txt),
``bforest-csv`` (.csv + .json), ``treeqsm-mat`` (.mat), ``ply`` (.ply), ``obj`` (.obj), the other
tools' CSV layouts ``simpleforest-csv`` and ``archi-csv`` (by name), and the synthetic laser scans
``las`` (.las, .laz) and ``xyz`` (.xyz).
"""

from bforest_core.hookspecs import hookimpl

from ._mat import CylDataMatReader, TreeQSMFlatReader, TreeQSMMatReader
from ._text import ArchiCSVReader, NativeCSVReader, SimpleForestCSVReader, TreeQSMTextReader
from .foreign_csv import ArchiCSVWriter, SimpleForestCSVWriter
from .raw_cylinders import QSMReadWarning
from .scan import LASWriter, XYZWriter
from .writers import CSVWriter, OBJWriter, PLYWriter, TreeQSMMatWriter, TreeQSMTextWriter

READERS = [
    TreeQSMMatReader,
    TreeQSMFlatReader,
    CylDataMatReader,
    TreeQSMTextReader,
    SimpleForestCSVReader,
    ArchiCSVReader,
    NativeCSVReader,
]
WRITERS = [
    TreeQSMTextWriter,
    CSVWriter,
    TreeQSMMatWriter,
    PLYWriter,
    OBJWriter,
    LASWriter,
    XYZWriter,
    SimpleForestCSVWriter,
    ArchiCSVWriter,
]

__all__ = ["READERS", "WRITERS", "QSMReadWarning", "bforest_components"]


@hookimpl
def bforest_components():
    return READERS + WRITERS
