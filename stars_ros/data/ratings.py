"""Load rating datasets: the SocNav1 per-annotator files, or the generic tabular format.

SocNav1 root (``raw/a.jsonl`` … or the ``raw`` folder itself): one file per annotator,
annotator = file name without extension; one JSON scene per line with ``identifier`` and a
0–100 ``score``, used on [0, 1] (score / 100). The single action is ``navigate``.
Scene identity is the full ``identifier``: "01892 A" and "01892 B" are different scenes
(different content and scores). The published StARS paper's 1.89 ratings per scene
(9,280 / 4,904) implies that it keyed items by the numeric prefix instead, merging such
pairs; ``item_keys('prefix')`` gives that keying for q_i and b_i (each rating is still
encoded from its own scene graph). When one identifier carries two different
scene contents (SocNav1 has one such case, ``01998 A``), each content becomes its own scene
keyed ``<identifier>#<first 8 hex digits of its content digest>``: both ratings are kept,
and no rating is attached to a scene its annotator did not see.

Generic root: ``annotations.csv`` with header ``user,scene,action,score`` and either
``scenes.csv`` (header ``scene`` then numeric feature columns; tabular encoders) or
``scenes.jsonl`` (one scene graph per line with a ``scene`` key; graph encoders).
Scores are on the scale the data declares (SocNav1: [0, 1]; generic: the lowest and
highest score in annotations.csv); predictions are clipped to it. A row of the evaluation
protocol is an *example*: one user's ratings of one scene, every action rated in it
(``RatingData.examples``), as in the paper, where each row is an annotator's rating of a
scene with all actions as targets.
Rules: every file must be non-empty; every score numeric and finite; every annotation's
scene listed in the scene file; a (user, scene, action) triple appears once; scene keys
are unique, and so are column names. Breaking a rule raises DataError naming the file and
line (the header is line 1). Scenes without ratings are kept (they cost nothing and may be
scored later). The CSV files are read with pandas.
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from stars_ros.errors import DataError, SceneGraphError
from stars_ros.files import atomic_write
from stars_ros.data.scene_graph import FEATURISER_VERSION, featurise
from stars_ros.data.scene_source import socnav1_root
from stars_ros.data.scene_store import GraphStore, TabularStore

log = logging.getLogger(__name__)
SOCNAV_ACTION = 'navigate'
SOCNAV_SCORE_SCALE = 100.0
ANNOTATION_COLUMNS = ('user', 'scene', 'action', 'score')


@dataclass
class RatingData:
    """Ratings as parallel arrays (one entry per rating) plus the scenes they refer to."""

    users: np.ndarray           # str, per rating
    scenes: np.ndarray          # int64 index into scene_keys / store, per rating
    actions: np.ndarray         # int64 index into action_names, per rating
    scores: np.ndarray          # float64 on the dataset's rating scale, per rating
    scene_keys: list
    store: object               # GraphStore or TabularStore, row i is scene_keys[i]
    action_names: tuple
    fingerprint: str
    source: str
    notes: list = field(default_factory=list)
    scale: tuple | None = None  # (lowest, highest) score a rating can take; None: unbounded
    keyings: dict = field(default_factory=dict)  # keying name -> item key per scene (see item_keys)

    def __len__(self) -> int:
        return len(self.scores)

    @property
    def examples(self) -> np.ndarray:
        """Example id per rating: ratings of one user on one scene (every action) share it.

        Folds, inner folds and sparsity samples are drawn over examples, never over single
        ratings: a test rating's siblings (the same person's other actions on the same scene)
        in the training rows would let a model memorise a per-(user, scene) mood.
        """
        pairs = np.stack([np.unique(self.users, return_inverse=True)[1].ravel(), self.scenes], axis=1)
        return np.unique(pairs, axis=0, return_inverse=True)[1].ravel()

    def item_keys(self, keying: str = 'identifier') -> list:
        """The item key of every scene row: ``identifier`` (the scene key itself) or another
        keying the loader provides (SocNav1: ``prefix``). Scenes sharing an item key share
        q_i and b_i."""
        if keying == 'identifier':
            return list(self.scene_keys)
        if keying not in self.keyings:
            raise DataError(f"item keying '{keying}' is not available for {self.source}; "
                            f"choices: {['identifier', *self.keyings]}")
        return list(self.keyings[keying])

    @property
    def kind(self) -> str:
        return self.store.kind


DATASETS = {'socnav1': socnav1_root}  # names load_dataset knows -> their root
LOADERS = ('socnav1', 'generic')


def load_dataset(path_or_name, kind: str | None = None) -> RatingData:
    """Load a data set by name (``'socnav1'``: at ``socnav1_root()``) or from a folder.

    A folder holding ``annotations.csv`` is read in the generic format, one holding
    ``raw/*.jsonl`` (or ``*.jsonl``) as SocNav1; ``kind`` ('socnav1' or 'generic') says
    which instead of looking. Raises DataError for anything else, naming the file and line
    of a fault."""
    if kind is not None and kind not in LOADERS:
        raise ValueError(f'unknown kind {kind!r}; choices: {list(LOADERS)}')
    name = str(path_or_name).lower()
    root = DATASETS[name]() if name in DATASETS and not Path(path_or_name).exists() else Path(path_or_name)
    if not root.is_dir():
        known = f" (or one of the names {sorted(DATASETS)})" if name not in DATASETS else ' (set STARS_SOCNAV1_ROOT)'
        raise DataError(f'{root}: no such data folder{known}')
    if kind == 'generic' or (kind is None and (root / 'annotations.csv').exists()):
        return load_generic(root)
    if kind == 'socnav1' or (root / 'raw').is_dir() or sorted(root.glob('*.jsonl')):
        return load_socnav1(root)
    raise DataError(f'{root}: neither a SocNav1 root (raw/*.jsonl) nor a generic root (annotations.csv)')


def _digest(paths) -> str:
    sha = hashlib.sha256()
    for path in paths:
        sha.update(path.name.encode() + b'\0' + path.read_bytes())
    return sha.hexdigest()


def _cache_path(fingerprint: str):
    """Where featurised graphs of data with this fingerprint are cached (None: caching off).

    ``STARS_ROS_CACHE`` names the folder (default ``~/.cache/stars_ros``; empty disables it).
    The key holds the featuriser version, so a change of features never reads a stale cache.
    """
    folder = os.environ.get('STARS_ROS_CACHE', str(Path.home() / '.cache' / 'stars_ros'))
    if not folder:
        return None
    return Path(folder) / f'graphs-v{FEATURISER_VERSION}-{fingerprint[:32]}.pt'


def _cached_graph_store(fingerprint: str, build) -> GraphStore:
    """``build()``'s GraphStore, read from the cache when this exact data was seen before."""
    path = _cache_path(fingerprint)
    if path is not None and path.exists():
        try:
            return GraphStore.load(path)
        except Exception as error:  # a damaged cache is rebuilt, never trusted
            log.warning('ignoring unreadable feature cache %s: %s', path, error)
    store = build()
    if path is not None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(path, store.save)
        except OSError as error:
            log.warning('cannot write feature cache %s: %s', path, error)
    return store


def _content_digest(scene: dict) -> str:
    content = {k: v for k, v in scene.items() if k not in ('identifier', 'score')}
    return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()


def _parse_json_line(path, number, line):
    try:
        return json.loads(line, parse_constant=_refuse_constant)
    except (json.JSONDecodeError, ValueError) as error:
        raise DataError(f'{path}:{number}: not valid JSON ({error})') from error


def _refuse_constant(name):
    raise ValueError(f'{name} is not a number')


def _score(path, number, value):
    try:
        score = float(value)
    except (TypeError, ValueError):
        raise DataError(f'{path}:{number}: score {value!r} is not a number') from None
    if isinstance(value, bool) or not math.isfinite(score):
        raise DataError(f'{path}:{number}: score {value!r} is not a finite number')
    return score


def _featurise_at(path, number, scene):
    try:
        return featurise(scene)
    except SceneGraphError as error:
        raise DataError(f'{path}:{number}: {error}') from error


def load_socnav1(root) -> RatingData:
    root = Path(root)
    folder = root / 'raw' if (root / 'raw').is_dir() else root
    paths = sorted(folder.glob('*.jsonl'))
    if not paths:
        raise DataError(f'{folder}: no annotator files (*.jsonl)')
    records = []  # (user, identifier, digest, score, path, line)
    contents = {}  # (identifier, digest) -> (scene, path, line)
    for path in paths:
        lines = path.read_text().splitlines()
        if not any(line.strip() for line in lines):
            raise DataError(f'{path}: empty file')
        for number, line in enumerate(lines, 1):
            if not line.strip():
                raise DataError(f'{path}:{number}: empty line')
            scene = _parse_json_line(path, number, line)
            if not isinstance(scene, dict) or 'identifier' not in scene or 'score' not in scene:
                raise DataError(f'{path}:{number}: expected an object with identifier and score')
            score = _score(path, number, scene['score'])
            if not 0.0 <= score <= SOCNAV_SCORE_SCALE:
                raise DataError(f'{path}:{number}: score {score} outside 0-100')
            identifier = str(scene['identifier'])
            digest = _content_digest(scene)
            contents.setdefault((identifier, digest), (scene, path, number))
            records.append((path.stem, identifier, digest, score / SOCNAV_SCORE_SCALE, path, number))

    variants = {}
    for identifier, digest in contents:
        variants.setdefault(identifier, []).append(digest)
    notes = []
    keys = {}
    for (identifier, digest) in contents:
        if len(variants[identifier]) > 1:
            keys[identifier, digest] = f'{identifier}#{digest[:8]}'
        else:
            keys[identifier, digest] = identifier
    for identifier, digests in variants.items():
        if len(digests) > 1:
            notes.append(f"identifier '{identifier}' has {len(digests)} different scene contents: "
                         'kept as scenes ' + ', '.join(f"'{identifier}#{d[:8]}'" for d in digests))
    scene_keys = list(dict.fromkeys(keys[k] for k in contents))
    index = {key: i for i, key in enumerate(scene_keys)}
    fingerprint = _digest(paths)
    store = _cached_graph_store(fingerprint, lambda: GraphStore(
        [_featurise_at(path, number, scene) for (scene, path, number) in contents.values()]))

    seen = {}
    for user, identifier, digest, _, path, number in records:
        pair = (user, keys[identifier, digest])
        if pair in seen:
            raise DataError(f'{path}:{number}: annotator {user} rates scene {pair[1]} again '
                            f'(first at line {seen[pair]})')
        seen[pair] = number
    return RatingData(
        users=np.array([r[0] for r in records]),
        scenes=np.array([index[keys[r[1], r[2]]] for r in records], dtype=np.int64),
        actions=np.zeros(len(records), dtype=np.int64),
        scores=np.array([r[3] for r in records]),
        scene_keys=scene_keys, store=store, action_names=(SOCNAV_ACTION,),
        fingerprint=fingerprint, source=str(folder), notes=notes, scale=(0.0, 1.0),
        keyings={'prefix': [key.split(' ')[0] for key in scene_keys]})


def _csv_cells(path, nrows=None) -> pd.DataFrame:
    """The records of a CSV as strings, the header row included, blank lines kept: a field
    a record lacks is NaN, an empty one ''. ParserError for a record longer than the first."""
    return pd.read_csv(path, header=None, dtype=str, keep_default_na=False, skip_blank_lines=False,
                       engine='python', nrows=nrows)


def _line_breaks(cells: pd.DataFrame) -> np.ndarray:
    """Line breaks inside each record's quoted fields: a record spans that many more lines."""
    return cells.apply(lambda column: column.str.count(r'\r\n|\r|\n')).sum(axis=1).to_numpy(dtype=np.int64)


def _read_csv(path, required_first) -> tuple:
    """(header, rows) of a CSV: rows as stripped strings in the header's columns, indexed by
    file line (the header is line 1), blank rows dropped. Checks the header, every row's
    field count and emptiness."""
    if not path.exists():
        raise DataError(f'{path}: file missing')
    too_long = None
    try:
        cells = _csv_cells(path)
    except pd.errors.EmptyDataError:
        raise DataError(f'{path}: empty file') from None
    except pd.errors.ParserError as error:  # a record with more fields than the header
        found = re.search(r'Expected (\d+) fields in line (\d+), saw (\d+)', str(error))
        if found is None:
            raise DataError(f'{path}: {error}') from None
        expected, record, saw = map(int, found.groups())
        cells = _csv_cells(path, nrows=record - 1)  # the records before it, checked first
        too_long = (record + int(_line_breaks(cells).sum()), saw)
    breaks = _line_breaks(cells)
    cells.index = 1 + np.arange(len(cells)) + np.cumsum(breaks) - breaks
    header = [name.strip() for name in cells.iloc[0].fillna('')] if len(cells) else []  # a lone line break: no header
    missing = [c for c in required_first if c not in header]
    if missing:
        raise DataError(f'{path}:1: missing columns {missing} (header is {header})')
    repeated = sorted({name for name in header if header.count(name) > 1})
    if repeated:
        raise DataError(f'{path}:1: repeated columns {repeated}')
    rows = cells.iloc[1:].apply(lambda column: column.str.strip())
    rows.columns = header
    rows = rows[rows.fillna('').ne('').any(axis=1)]
    fields = cells.loc[rows.index].notna().sum(axis=1)
    short = fields < len(header)
    if short.any():
        line = short.idxmax()
        raise DataError(f'{path}:{line}: {fields[line]} fields, header has {len(header)}')
    if too_long is not None:
        raise DataError(f'{path}:{too_long[0]}: {too_long[1]} fields, header has {len(header)}')
    if rows.empty:
        raise DataError(f'{path}: no data rows')
    return header, rows


def _numbers(column: pd.Series) -> tuple:
    """(values, not a number, not finite) of a column of strings, read as ``float`` reads
    them ('nan' is a number that is not finite)."""
    values = pd.to_numeric(column, errors='coerce')
    not_number = values.isna() & ~column.str.fullmatch(r'[+-]?nan', case=False)
    return values, not_number, ~np.isfinite(values) & ~not_number


def _raise_first(path, problems) -> None:
    """Raise DataError for the first line at fault: ``problems`` are (mask over lines,
    message of a line), in the order one line is checked; the earliest line wins."""
    found = [(mask.idxmax(), k) for k, (mask, _) in enumerate(problems) if mask.any()]
    if found:
        line, k = min(found)
        raise DataError(f'{path}:{line}: {problems[k][1](line)}')


def _first_line(column: pd.Series, line) -> int | None:
    """The line where ``column``'s value at ``line`` first occurs, None if there."""
    first = column.index[column == column[line]][0]
    return None if first == line else first


def _load_generic_scenes(root):
    """Scene keys and store from scenes.csv (tabular) or scenes.jsonl (graphs)."""
    table, lines = root / 'scenes.csv', root / 'scenes.jsonl'
    if table.exists() == lines.exists():
        raise DataError(f'{root}: needs exactly one of scenes.csv or scenes.jsonl')
    if table.exists():
        header, rows = _read_csv(table, ['scene'])
        names = [h for h in header if h != 'scene']
        if not names:
            raise DataError(f'{table}:1: no feature columns after scene')
        keys = rows['scene']
        problems = [(keys.eq('') | keys.duplicated(), lambda line: (
            f'scene key {keys[line]!r} empty or repeated (first at line {_first_line(keys, line)})'))]
        features = []
        for name in names:
            values, not_number, not_finite = _numbers(rows[name])
            problems += [
                (not_number, lambda line, name=name: f'column {name} value {rows[name][line]!r} is not a number'),
                (not_finite, lambda line, name=name: f'column {name} is not finite')]
            features.append(values.to_numpy(dtype=np.float64))
        _raise_first(table, problems)
        return keys.tolist(), TabularStore(np.stack(features, axis=1), names), table
    keys, where = [], {}
    graphs = []
    text = lines.read_text().splitlines()
    for number, line in enumerate(text, 1):
        if not line.strip():
            continue
        scene = _parse_json_line(lines, number, line)
        key = scene.get('scene') if isinstance(scene, dict) else None
        if not isinstance(key, str) or not key or key in where:
            raise DataError(f'{lines}:{number}: scene key {key!r} missing, empty or repeated')
        where[key] = number
        keys.append(key)
        graphs.append(_featurise_at(lines, number, scene))
    if not graphs:
        raise DataError(f'{lines}: empty file')
    return keys, GraphStore(graphs), lines


def load_generic(root) -> RatingData:
    root = Path(root)
    keys, store, scene_file = _load_generic_scenes(root)
    path = root / 'annotations.csv'
    _, rows = _read_csv(path, ANNOTATION_COLUMNS)
    index = {key: i for i, key in enumerate(keys)}
    triples = list(ANNOTATION_COLUMNS[:3])
    scores, not_number, not_finite = _numbers(rows['score'])
    empty = [(rows[column].eq(''), lambda line, column=column: f'{column} is empty') for column in ANNOTATION_COLUMNS]
    _raise_first(path, empty + [
        (~rows['scene'].isin(keys), lambda line: f"scene {rows['scene'][line]!r} is not in {scene_file.name}"),
        (rows.duplicated(triples), lambda line: (
            f'duplicate rating of {tuple(rows.loc[line, triples])} (first at line '
            f'{rows.index[(rows[triples] == rows.loc[line, triples]).all(axis=1)][0]})')),
        (not_number, lambda line: f"score {rows['score'][line]!r} is not a number"),
        (not_finite, lambda line: f"score {rows['score'][line]!r} is not a finite number")])
    action_names = tuple(sorted(set(rows['action'])))
    action_index = {name: i for i, name in enumerate(action_names)}
    scores = scores.to_numpy(dtype=np.float64)
    return RatingData(
        users=np.array(rows['user'].tolist()), scenes=rows['scene'].map(index).to_numpy(dtype=np.int64),
        actions=rows['action'].map(action_index).to_numpy(dtype=np.int64),
        scores=scores, scene_keys=keys, store=store, action_names=action_names,
        fingerprint=_digest([path, scene_file]), source=str(root), scale=(float(scores.min()), float(scores.max())))
