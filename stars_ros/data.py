"""Load rating datasets: the SocNav1 per-annotator files, or the generic tabular format.

SocNav1 root (``raw/a.jsonl`` … or the ``raw`` folder itself): one file per annotator,
annotator = file name without extension; one JSON scene per line with ``identifier`` and a
0–100 ``score``, used on [0, 1] (score / 100). The single action is ``navigate``.
Scene identity is the full ``identifier``: "01998 A" and "01998 B" are different scenes
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
are unique. Breaking a rule raises DataError naming the file and line. Scenes without
ratings are kept (they cost nothing and may be scored later).
"""
from __future__ import annotations

import csv
import hashlib
import json
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import DataError, SceneGraphError
from .scene_graph import FEATURISER_VERSION, featurise
from .scene_store import GraphStore, TabularStore

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


def load_dataset(root) -> RatingData:
    """Load a SocNav1 root or a generic-format root, whichever ``root`` holds."""
    root = Path(root)
    if (root / 'annotations.csv').exists():
        return load_generic(root)
    if (root / 'raw').is_dir() or sorted(root.glob('*.jsonl')):
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
            temporary = path.with_suffix(f'.{os.getpid()}.tmp')
            store.save(temporary)
            os.replace(temporary, path)
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


def _read_csv(path, required_first):
    """Rows of a CSV as (line number, dict); checks header and emptiness."""
    if not path.exists():
        raise DataError(f'{path}: file missing')
    with path.open(newline='') as handle:
        reader = csv.reader(handle)
        header = next(reader, None)
        if header is None:
            raise DataError(f'{path}: empty file')
        header = [h.strip() for h in header]
        missing = [c for c in required_first if c not in header]
        if missing:
            raise DataError(f'{path}:1: missing columns {missing} (header is {header})')
        rows = []
        for row in reader:
            number = reader.line_num
            if not any(cell.strip() for cell in row):
                continue
            if len(row) != len(header):
                raise DataError(f'{path}:{number}: {len(row)} fields, header has {len(header)}')
            rows.append((number, dict(zip(header, (cell.strip() for cell in row)))))
    if not rows:
        raise DataError(f'{path}: no data rows')
    return header, rows


def _load_generic_scenes(root):
    """Scene keys and store from scenes.csv (tabular) or scenes.jsonl (graphs)."""
    table, lines = root / 'scenes.csv', root / 'scenes.jsonl'
    if table.exists() == lines.exists():
        raise DataError(f'{root}: needs exactly one of scenes.csv or scenes.jsonl')
    keys, where = [], {}
    if table.exists():
        header, rows = _read_csv(table, ['scene'])
        names = [h for h in header if h != 'scene']
        if not names:
            raise DataError(f'{table}:1: no feature columns after scene')
        features = np.empty((len(rows), len(names)))
        for r, (number, row) in enumerate(rows):
            key = row['scene']
            if not key or key in where:
                raise DataError(f'{table}:{number}: scene key {key!r} empty or repeated (first at line {where.get(key)})')
            where[key] = number
            keys.append(key)
            for c, name in enumerate(names):
                try:
                    features[r, c] = float(row[name])
                except ValueError:
                    raise DataError(f'{table}:{number}: column {name} value {row[name]!r} is not a number') from None
                if not math.isfinite(features[r, c]):
                    raise DataError(f'{table}:{number}: column {name} is not finite')
        return keys, TabularStore(features, names), table
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
    seen = {}
    users, scenes, actions, scores = [], [], [], []
    for number, row in rows:
        for column in ANNOTATION_COLUMNS:
            if not row[column]:
                raise DataError(f'{path}:{number}: {column} is empty')
        if row['scene'] not in index:
            raise DataError(f"{path}:{number}: scene {row['scene']!r} is not in {scene_file.name}")
        triple = (row['user'], row['scene'], row['action'])
        if triple in seen:
            raise DataError(f'{path}:{number}: duplicate rating of {triple} (first at line {seen[triple]})')
        seen[triple] = number
        users.append(row['user'])
        scenes.append(index[row['scene']])
        actions.append(row['action'])
        scores.append(_score(path, number, row['score']))
    action_names = tuple(sorted(set(actions)))
    action_index = {name: i for i, name in enumerate(action_names)}
    return RatingData(
        users=np.array(users), scenes=np.array(scenes, dtype=np.int64),
        actions=np.array([action_index[a] for a in actions], dtype=np.int64),
        scores=np.array(scores), scene_keys=keys, store=store, action_names=action_names,
        fingerprint=_digest([path, scene_file]), source=str(root), scale=(min(scores), max(scores)))
