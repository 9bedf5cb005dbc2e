"""Something-Something-v2 label files → clip records.

SSv2 ships four JSON files: `something-something-v2-{train,validation,test}.json` (lists of entries)
and `something-something-v2-labels.json` (class name → index as a string). Train and validation entries
carry `id`, `label` (the caption), `template` (the class name with brackets around the placeholders) and
`placeholders`; test entries carry only `id`. The class index is
`labels[template.replace("[", "").replace("]", "")]`: strip only the brackets, because the bracket
contents are not always "something" and some class names contain commas.
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

SPLITS = ("train", "validation", "test")
NO_LABEL = -1
MAX_CLASS_INDEX = 2**31 - 1  # class indices travel as 64-bit integers; SSv2 has 174 classes


class AnnotationError(ValueError):
    """A label file is missing or malformed; the message names the file and what to do."""


@dataclass(frozen=True)
class ClipRecord:
    id: str
    split: str
    caption: str = ""
    template: str = ""
    class_index: int = NO_LABEL


def annotation_path(annotations: Path, name: str) -> Path:
    return Path(annotations) / f"something-something-v2-{name}.json"


def class_name(template: str) -> str:
    """`"Putting [something] onto [a slanted surface]"` → `"Putting something onto a slanted surface"`."""
    return template.replace("[", "").replace("]", "")


class _RepeatedKey(ValueError):
    pass


def _object(pairs: list[tuple[str, object]]) -> dict:
    """A JSON object, refused where it gives a key twice (JSON keeps the last without a word)."""
    if repeated := [key for key, count in Counter(key for key, _ in pairs).items() if count > 1]:
        raise _RepeatedKey(repeated[0])
    return dict(pairs)


def _read_json(path: Path):
    if not path.is_file():
        raise AnnotationError(f"{path}: file not found; --annotations must be the directory holding the four "
                              "something-something-v2-*.json files")
    try:
        text = path.read_text(encoding="utf-8")
        data = json.loads(text, object_pairs_hook=_object)
    except _RepeatedKey as error:
        raise AnnotationError(f"{path}: the key {error.args[0]!r} appears twice in one object (JSON would keep the "
                              "last): keep one") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise AnnotationError(f"{path}: not valid JSON ({error})") from None
    except (ValueError, RecursionError) as error:  # a number of over 4,300 digits; arrays nested thousands deep
        raise AnnotationError(f"{path}: JSON that Python cannot read ({type(error).__name__}: "
                              f"{str(error).split(';')[0][:120]}); SSv2's label files hold no such value") from None
    try:
        json.dumps(data, ensure_ascii=False).encode("utf-8")  # one pass over every string, at C speed
    except UnicodeEncodeError:
        raise AnnotationError(f"{path}: the text {ascii(_with_a_lone_surrogate(data))[:80]} holds half of a UTF-16 pair "
                              "(an emoji cut in half, as JavaScript's string slicing leaves it): no file name or text "
                              "encoding can hold it; remove it") from None
    return data


def _with_a_lone_surrogate(value: object) -> str | None:
    """The first string in a JSON value that holds a lone UTF-16 surrogate (a pair escaped whole, e.g. \\ud83d\\ude00,
    decodes to one character), or None."""
    if isinstance(value, str):
        try:
            value.encode("utf-8")
            return None
        except UnicodeEncodeError:
            return value
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, item in items:
        if (found := _with_a_lone_surrogate(key) or _with_a_lone_surrogate(item)) is not None:
            return found
    return None


def load_labels(annotations: Path) -> dict[str, int]:
    """Class name (brackets stripped) → class index."""
    path = annotation_path(annotations, "labels")
    labels = _read_json(path)
    if not isinstance(labels, dict):
        raise AnnotationError(f"{path}: expected an object mapping class names to indices")
    for name, index in labels.items():  # SSv2 writes the indices as strings of digits
        if isinstance(index, bool) or not (isinstance(index, int) and index >= 0 or isinstance(index, str)
                                           and index.isascii() and index.isdigit()):
            raise AnnotationError(f"{path}: class {name!r} has index {index!r}; an index must be a whole number ≥ 0 "
                                  "(or a string of the digits 0-9, as SSv2 writes them)")
    indices = {name: int(index) for name, index in labels.items()}
    class_of: dict[int, str] = {}
    for name, index in indices.items():
        if index > MAX_CLASS_INDEX:
            raise AnnotationError(f"{path}: class {name!r} has index {index}, more than {MAX_CLASS_INDEX}: number the "
                                  "classes 0, 1, 2, …")
        if class_of.setdefault(index, name) != name:
            raise AnnotationError(f"{path}: classes {class_of[index]!r} and {name!r} share index {index}; each class "
                                  "needs its own")
    return indices


def _field(path: Path, position: int, entry: dict, name: str) -> str:
    """Entry `position`'s string field `name`, or an `AnnotationError` naming the file, the entry and the field."""
    if name not in entry:
        raise AnnotationError(f"{path}: entry {position} (id {entry['id']!r}) has no field {name!r}; train and "
                              "validation entries carry \"id\", \"label\", \"template\" and \"placeholders\"")
    if not isinstance(entry[name], str):
        raise AnnotationError(f"{path}: entry {position} (id {entry['id']!r}): field {name!r} must be a string, "
                              f"got {json.dumps(entry[name])[:80]}")
    return entry[name]


def load_split(annotations: Path, split: str, labels: dict[str, int] | None = None) -> list[ClipRecord]:
    """The clips of one split, in the file's order; `labels` defaults to the labels file next to it."""
    if split not in SPLITS:
        raise AnnotationError(f"unknown split {split!r}; choose from {', '.join(SPLITS)}")
    path = annotation_path(annotations, split)
    entries = _read_json(path)
    if not isinstance(entries, list):
        raise AnnotationError(f"{path}: expected a list of clip entries")
    labels = {} if split == "test" else load_labels(annotations) if labels is None else labels
    records: list[ClipRecord] = []
    first_of: dict[str, int] = {}  # id -> its entry's position
    for position, entry in enumerate(entries):
        if not isinstance(entry, dict) or "id" not in entry:
            raise AnnotationError(f"{path}: entry {position} is not an object with an \"id\": {str(entry)[:80]}")
        if isinstance(entry["id"], bool) or not isinstance(entry["id"], (str, int)):
            raise AnnotationError(f"{path}: entry {position} has id {json.dumps(entry['id'])[:80]}; an id must be a "
                                  "string or a whole number (the name of its video, <id>.webm)")
        clip_id = str(entry["id"])
        if clip_id in first_of:  # shards key clips by id: a repeat would make two samples of one key
            raise AnnotationError(f"{path}: entries {first_of[clip_id]} and {position} both have id {clip_id!r}; "
                                  "each clip must appear once: remove the repeat")
        first_of[clip_id] = position
        if split == "test":  # no labels: the test split's entries are ids only
            records.append(ClipRecord(id=clip_id, split=split))
            continue
        template, caption = _field(path, position, entry, "template"), _field(path, position, entry, "label")
        if class_name(template) not in labels:
            raise AnnotationError(f"{path}: entry {position} (id {clip_id!r}): its class {class_name(template)!r} "
                                  f"(the template without brackets) is not a key of {annotation_path(annotations, 'labels')}")
        records.append(ClipRecord(id=clip_id, split=split, caption=caption, template=template,
                                  class_index=labels[class_name(template)]))
    return records
