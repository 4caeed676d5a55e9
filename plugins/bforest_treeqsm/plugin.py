"""Entry point of the ``bforest_treeqsm`` plugin: TreeQSM's formats (the other tools' formats, meshes
and scans are the ``bforest_formats`` plugin's).

Readers (``bf.read_qsm``; detected from content, or by ``reader=<name>``):

========================  =====================================================================
``treeqsm-mat``           TreeQSM 2.3/2.4 structs ``qsm``/``QSM``/``OptQSM``/``QSMs`` (MAT v5, v7.3)
``treeqsm-flat``          TreeQSM 2.0 flat variables and the older v7.3 flat layout (pines)
``cyldata-mat``           the 14-column ``CylData`` matrix in a ``.mat`` file
``treeqsm-text``          TreeQSM text: 17 columns + header, 15-column layouts, 14-column text
========================  =====================================================================

Writers (``bf.write_tree``; by suffix or ``format=<name>``): ``treeqsm-text`` (.txt) and
``treeqsm-mat`` (.mat).
"""

from bforest_core.hookspecs import hookimpl

from ._mat import CylDataMatReader, TreeQSMFlatReader, TreeQSMMatReader
from ._text import TreeQSMTextReader
from .writers import TreeQSMMatWriter, TreeQSMTextWriter

READERS = [TreeQSMMatReader, TreeQSMFlatReader, CylDataMatReader, TreeQSMTextReader]
WRITERS = [TreeQSMTextWriter, TreeQSMMatWriter]

__all__ = ["READERS", "WRITERS", "bforest_components"]


@hookimpl
def bforest_components():
    return READERS + WRITERS
