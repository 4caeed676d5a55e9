"""The sample trees: real QSMs from the public repositories they were published in.

Bayes Forest ships no tree file (several sources state no licence, so their files are fetched for
the user's own use, never redistributed). ``bforest data fetch NAME`` downloads a sample from the
commit of its repository that the project was tested with, checks its SHA-256 and keeps it in a
cache folder; ``sample:NAME`` then names it wherever a QSM path goes (``bforest info``, ``init``,
``distance``, ``[target] qsm`` of a recipe), and ``bforest data list`` says where each comes from
and under what licence.

The cache folder is ``$BFOREST_DATA_DIR`` when set, else ``$XDG_CACHE_HOME/bayesforest/samples``
(``~/.cache/bayesforest/samples``; ``%LOCALAPPDATA%`` on Windows). ``$BFOREST_DATA_MIRROR`` names
a mirror (a URL, or a folder) holding the files under their sample file names, which is fetched
from instead of the sources: an institute's copy behind a firewall, or a test's local server.
"""

from __future__ import annotations

import difflib
import hashlib
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

from .errors import BayesForestError

#: what names a sample where a QSM path goes
PREFIX = "sample:"
#: environment variables: the cache folder, and a mirror fetched from instead of the sources
DATA_DIR_ENV = "BFOREST_DATA_DIR"
MIRROR_ENV = "BFOREST_DATA_MIRROR"
#: seconds a download may wait for its source before it gives up
TIMEOUT = 30.0

_RAW = "https://raw.githubusercontent.com"
_NO_LICENCE = "none stated by the repository: fetched for your own use; do not redistribute"
_PINES = ("inuritdino/SFennica-Lignum-SSM", "2a36c40a956341b2865ea5899b07c3dee9de8015")
_WYTHAM = ("TobyDJackson/WindAndTrees_FEM", "39775c75a4ca36676146bec0dc31ef7fa0c5042d")
_ITSME = ("lmterryn/ITSMe", "0f64b1cc579de7ffe112e50afc2e186e4ca9701e")
_PINES_PAPER = "Potapov et al. 2016, Silva Fennica 50(1), article 1413 (pine 3 is the paper's tree)"
_WYTHAM_PAPER = (
    "Jackson et al. 2019, Finite element analysis of trees in the wind based on terrestrial laser "
    "scanning data, Agricultural and Forest Meteorology 265: 137-144"
)
_ITSME_CITE = "the ITSMe R package's test data (github.com/lmterryn/ITSMe)"


class SampleError(BayesForestError):
    """A sample that is unknown, not fetched, or cannot be fetched (the message says which)."""


@dataclass(frozen=True)
class Sample:
    """One sample tree: where it comes from, its licence and the file's SHA-256."""

    name: str
    filename: str
    repository: str  # owner/name on GitHub
    commit: str
    path: str  # in the repository
    licence: str
    sha256: str
    size: int  # bytes
    about: str
    cite: str

    @property
    def url(self) -> str:
        """The file at the commit the project was tested with."""
        return f"{_RAW}/{self.repository}/{self.commit}/{self.path}"

    @property
    def source(self) -> str:
        """``owner/name path`` of the repository's file."""
        return f"{self.repository} {self.path}"


def _pine(k: int, sha: str, size: int, about: str) -> Sample:
    return Sample(
        f"pine_ruotsinkyla_{k}",
        f"pine_ruotsinkyla_{k}.mat",
        *_PINES,
        f"qsm_library/pine_Ruotsinkyla_tree{k}_model1.mat",
        _NO_LICENCE,
        sha,
        size,
        f"Scots pine (Pinus sylvestris), Ruotsinkylä, Finland; TreeQSM MAT v7.3; {about}",
        _PINES_PAPER,
    )


def _wytham(k: int, leaf_off: bool, sha: str, size: int, about: str) -> Sample:
    return Sample(
        f"wytham_tf{k}",
        f"wytham_tf{k}.mat",
        *_WYTHAM,
        f"QSMs/cyl_data_Tf{k}{'_LeafOff' if leaf_off else ''}_Validation_1_1.mat",
        _NO_LICENCE,
        sha,
        size,
        f"broadleaved tree of Wytham Woods, UK (species not stated); CylData n x 14 MAT; {about}",
        _WYTHAM_PAPER,
    )


def _itsme(name: str, path: str, sha: str, size: int, about: str) -> Sample:
    return Sample(name, f"{name}.mat", *_ITSME, path, "MIT", sha, size, about, _ITSME_CITE)


#: every sample, by name (SHA-256 and size of the file the project's tests read)
SAMPLES: dict[str, Sample] = {
    s.name: s
    for s in [
        _pine(1, "252354861463fd1a5d159bad38573d0ec19610beaf31c91925e6333b377c437b", 204512, "2726 cylinders, 13.3 m"),
        _pine(2, "f809d33a1f8f32fcbf0002b6f6785dd5267077bf03eeaecc329e6eff08fddf74", 177500, "2248 cylinders, 11.1 m"),
        _pine(3, "21033dbaff8a476265b5f3b164a96f30ae1b37708ca8ac443bd96ecf0ff7859c", 100403, "876 cylinders, 9.9 m"),
        _wytham(1, True, "70e507e5bd94da25cb4158f69147554bc1f7134c3ae7a64f57fc16cc0b4a562e", 82671, "18.3 m"),
        _wytham(2, True, "4457c90189436a5b973a04c87f7caf1208f10cec9c23d453b1aa07de1d29dc6d", 40143, "17.4 m"),
        _wytham(3, True, "bf1e1e1a8fa97fefe403a66cc9b8f556ef1132fa5544edc127974180a1e309b4", 20202, "17.9 m"),
        _wytham(4, False, "916c0a943087c938b59ef439bd3b937f6a4c524aeb37e38b508c9302299ad2ea", 54418, "19.7 m"),
        _wytham(5, False, "2ddfbd26fec480478735a8516ab14eb140313c918a64e1ab45240b8f25894ec8", 42136, "19.8 m"),
        Sample(
            "coffeetree_archi",
            "coffeetree_archi.csv",
            "aidanmorales/rTwig",
            "50494b4b2425daef70db3783e6aecbb81cca8765",
            "inst/extdata/QSM2.csv",
            "GPL (>= 3)",
            "97cf0182194412d10f362bb2ec9f15990b518dc05dd9b3931c63d29a5d9e1df8",
            201429,
            "Kentucky coffeetree (Gymnocladus dioicus); aRchi CSV; 1231 cylinders, 3.7 m",
            "the rTwig R package's example data (github.com/aidanmorales/rTwig)",
        ),
        Sample(
            "archi_tree1_treeqsm_v23",
            "archi_tree1_treeqsm_v23.txt",
            "umr-amap/aRchi",
            "9ade188cd63cc50b494e95b3cb56643cc19c6366",
            "inst/extdata/Tree_1_TreeQSM.txt",
            "CeCILL",
            "1d312a607ff1c8cfa6f9668bf479665aefc994e6f3a33d6e3aa6ac8c97bd1b46",
            249775,
            "tree of the aRchi package (species not stated); TreeQSM 2.3 text, 15 columns; 2271 cylinders, 22.0 m",
            "the aRchi R package's example data (github.com/umr-amap/aRchi)",
        ),
        _itsme(
            "itsme_qsm_tree_v200",
            "tests/qsms/qsm_tree_v200.mat",
            "61b65a2d846c1096c9f1da2e0ee403defa3216b547c1c4197b2b18d5a9a8ec3b",
            100275,
            "TreeQSM 2.0 flat variables; 115 cylinders, 5.4 m",
        ),
        _itsme(
            "itsme_qsm_tree_v230",
            "tests/qsms/qsm_tree_v230.mat",
            "52ec54cd096290004d48cee6d9678a92f97571e6c214acec750d7c2b2ab6d9b6",
            6110,
            "TreeQSM 2.3, one QSMs entry; 88 cylinders, 20.8 m",
        ),
        _itsme(
            "itsme_qsm_tree_v230_notria",
            "tests/qsms/qsm_tree_v230_notria.mat",
            "455a938391133781a8b5e35288763d62d77e25cfc388f756e506cbd0f2374517",
            78351,
            "TreeQSM 2.3; 1807 cylinders, 28.1 m",
        ),
        _itsme(
            "itsme_qsm_tree_v240",
            "tests/qsms/qsm_tree_v240.mat",
            "bf97e9b9e4acdb0480f43f2c25a9a304be92a6b19136ebed819457fdd9307681",
            218183,
            "TreeQSM 2.4.0 with triangulation; 3791 cylinders, 28.4 m",
        ),
        _itsme(
            "itsme_qsm_trunk",
            "tests/qsms/qsm_trunk.mat",
            "1154bf83b462ed700e763cb52d4ecb64e3fdc3ed81fb6f03794d0e832ba4e001",
            51216,
            "TreeQSM 2.4.0, a trunk only; 48 cylinders, 24.0 m",
        ),
        _itsme(
            "itsme_qsms_tree_v230",
            "tests/qsms/qsms_tree_v230.mat",
            "d7f60eb7e20f9b22376b59e76c78df27fad6a5d0a8beb8984afc1930e03f67d6",
            27154,
            "TreeQSM 2.3, 4 reconstructions of one tree; 21 m",
        ),
        _itsme(
            "itsme_qsms_tree_v240_notria",
            "tests/qsms/qsms_tree_v240_notria.mat",
            "71de394f6a5b542d406f1c0f5970dcb8aaf605b40ec28048a378e18752538e7a",
            77345,
            "TreeQSM 2.4.0, 10 reconstructions of one tree; 21 m",
        ),
    ]
}


def data_dir() -> Path:
    """Return the folder the fetched samples are kept in (see the module text).

    Returns
    -------
    Path
        ``$BFOREST_DATA_DIR``, else the user's cache folder's ``bayesforest/samples``.
    """
    if os.environ.get(DATA_DIR_ENV):
        return Path(os.environ[DATA_DIR_ENV]).expanduser()
    return cache_dir() / "samples"


def cache_dir() -> Path:
    """Return Bayes Forest's folder in the user's cache folder.

    Returns
    -------
    Path
        ``$XDG_CACHE_HOME/bayesforest`` (``~/.cache/bayesforest``; on Windows under
        ``%LOCALAPPDATA%``): the fetched samples, the amortised estimator's compiled code.
    """
    if os.environ.get("XDG_CACHE_HOME"):
        base = Path(os.environ["XDG_CACHE_HOME"])
    elif os.name == "nt" and os.environ.get("LOCALAPPDATA"):
        base = Path(os.environ["LOCALAPPDATA"])
    else:
        base = Path.home() / ".cache"
    return base / "bayesforest"


def sample(name: str) -> Sample:
    """Return the sample called ``name``.

    Parameters
    ----------
    name : str
        A sample's name (``bforest data list``), with or without ``sample:``.

    Returns
    -------
    Sample
        Its entry.

    Raises
    ------
    SampleError
        For an unknown name (naming the closest ones).
    """
    name = name.removeprefix(PREFIX)
    if name not in SAMPLES:
        close = difflib.get_close_matches(name, list(SAMPLES), n=3, cutoff=0.5)
        hint = f"; did you mean {', '.join(close)}?" if close else " (bforest data list names them)"
        raise SampleError(f"unknown sample {name!r}{hint}")
    return SAMPLES[name]


def is_sample(path) -> bool:
    """Tell whether ``path`` names a sample (``sample:NAME``) rather than a file.

    Parameters
    ----------
    path : str or Path
        A QSM path as a user wrote it.

    Returns
    -------
    bool
        True for ``sample:NAME``.
    """
    return isinstance(path, str) and path.startswith(PREFIX)


def resolve(path) -> Path:
    """Return the file a QSM path names: a fetched sample's for ``sample:NAME``, else the path.

    Parameters
    ----------
    path : str or Path
        A file, or ``sample:NAME``.

    Returns
    -------
    Path
        The file (a sample's in :func:`data_dir`).

    Raises
    ------
    SampleError
        An unknown sample, or one not fetched yet (the message says how to fetch it).
    """
    if not is_sample(path):
        return Path(path)
    s = sample(path)
    p = data_dir() / s.filename
    if not p.is_file():
        raise SampleError(
            f"{path}: not fetched yet (looked in {p.parent}); fetch it with 'bforest data fetch {s.name}'"
        )
    return p


def stem(path) -> str:
    """Name what a QSM path holds (``bforest init`` names its recipe and run by it).

    ``"wytham_tf3"`` for both ``sample:wytham_tf3`` and ``data/wytham_tf3.mat``.

    Parameters
    ----------
    path : str or Path
        As :func:`resolve` takes it.

    Returns
    -------
    str
        The sample's name, else the file's name without its suffix.
    """
    return str(path).removeprefix(PREFIX) if is_sample(path) else Path(path).stem


def sha256_of(path) -> str:
    """Return the hex SHA-256 digest of the file at ``path``, read in blocks of 1 MiB.

    Parameters
    ----------
    path : str or Path
        Any readable file: a fetched sample, or one to compare with the catalogue.

    Returns
    -------
    str
        64 hex digits, as :attr:`Sample.sha256` holds them.
    """
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def fetch(name: str, dest=None, overwrite: bool = False, mirror: str | None = None) -> tuple[Path, bool]:
    """Download a sample into ``dest`` (default :func:`data_dir`) and check its SHA-256.

    Parameters
    ----------
    name : str
        The sample's name.
    dest : str or Path, optional
        The folder to write it to.
    overwrite : bool
        Replace a file of the sample's name in ``dest`` that is not the sample (a file that is,
        byte for byte, is kept as it is).
    mirror : str, optional
        A URL or folder holding the files under their sample file names, fetched from instead of
        the source (default ``$BFOREST_DATA_MIRROR``).

    Returns
    -------
    (Path, bool)
        The file, and whether it was downloaded (False: it was there already).

    Raises
    ------
    SampleError
        Unknown name; the source unreachable or answering with an error; a file that is not the
        one the project was tested with (nothing is written then); a file in the way.
    """
    s = sample(name)
    dest = Path(dest) if dest is not None else data_dir()
    out = dest / s.filename
    if out.is_file():
        if sha256_of(out) == s.sha256:
            return out, False
        if not overwrite:
            raise SampleError(f"{out}: exists and is not the sample {s.name}; replace it with --overwrite")
    mirror = os.environ.get(MIRROR_ENV) if mirror is None else mirror
    url = f"{mirror.rstrip('/')}/{s.filename}" if mirror else s.url
    try:
        dest.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SampleError(f"{dest}: cannot be created ({exc.strerror or exc})") from None
    fd, tmp = tempfile.mkstemp(prefix=f".{s.filename}.", dir=dest)
    try:
        with os.fdopen(fd, "wb") as fh:
            digest = _download(url, fh)
        if digest != s.sha256:
            raise SampleError(
                f"{url}: not the file Bayes Forest was tested with (SHA-256 {digest[:12]}..., expected "
                f"{s.sha256[:12]}...): its source may have changed; nothing was written"
            )
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out, True


def _download(url: str, fh) -> str:
    """Copy ``url`` (a URL, or a file path of a mirror folder) into ``fh``; return its SHA-256."""
    import urllib.error
    import urllib.request

    h = hashlib.sha256()

    def copy(src):
        for block in iter(lambda: src.read(1 << 16), b""):
            h.update(block)
            fh.write(block)

    if "://" not in url:  # a mirror that is a folder
        try:
            with open(url, "rb") as src:
                copy(src)
        except OSError as exc:
            raise SampleError(f"{url}: cannot be read ({exc.strerror or exc})") from None
        return h.hexdigest()
    try:
        with urllib.request.urlopen(url, timeout=TIMEOUT) as src:
            copy(src)
    except urllib.error.HTTPError as exc:
        raise SampleError(f"{url}: the server answered {exc.code} {exc.reason}") from None
    except (urllib.error.URLError, OSError) as exc:  # no network, no such host, refused, timed out
        reason = getattr(exc, "reason", None) or exc
        raise SampleError(
            f"cannot reach {url} ({reason}); check the connection, or set {MIRROR_ENV} to a mirror of the files"
        ) from None
    return h.hexdigest()
