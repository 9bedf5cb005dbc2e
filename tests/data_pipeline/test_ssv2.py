"""Parsing SSv2's label files: bracket stripping, the unlabelled test split, clear errors."""

import json

import pytest

from data_pipeline.ssv2 import NO_LABEL, AnnotationError, class_name, load_labels, load_split


def write(directory, name, data):
    (directory / f"something-something-v2-{name}.json").write_text(json.dumps(data))


@pytest.fixture
def annotations(tmp_path):
    write(tmp_path, "labels", {
        "Putting something onto a slanted surface but it doesn't glide down": "0",
        "Tipping something with something in it over, so something in it falls out": "1",
        "Pushing something from left to right": "2",
    })
    write(tmp_path, "train", [
        {"id": "78687", "label": "putting a pen onto a book but it doesn't glide down",
         "template": "Putting [something] onto [a slanted surface] but it doesn't glide down",
         "placeholders": ["a pen", "a book"]},
        {"id": "42326", "label": "tipping cup with water in it over, so water falls out",
         "template": "Tipping [something] with [something in it] over, so [something in it] falls out",
         "placeholders": ["cup", "water", "water"]},
        {"id": "3", "label": "pushing a box from left to right", "template": "Pushing [something] from left to right",
         "placeholders": ["a box"]},
    ])
    write(tmp_path, "test", [{"id": "1420"}, {"id": "55"}])
    return tmp_path


@pytest.mark.parametrize("name, text, message", [
    ("train", '[{"id": "3", "label": "pushing \\ud83d box", "template": "Pushing [something] from left to right"}]',
     r"train.json: the text 'pushing \\ud83d box' holds half of a UTF-16 pair \(an emoji cut in half"),
    ("labels", '{"Pushing something from left to right": "2", "Pushing something from left to right": "4"}',
     r"labels.json: the key 'Pushing something from left to right' appears twice in one object"),
    ("train", '[{"id": "3", "label": "a", "template": "Pushing [something] from left to right", "template": "b"}]',
     r"train.json: the key 'template' appears twice in one object"),
    # valid JSON that Python's reader refuses with a bare ValueError or RecursionError (a traceback)
    ("train", '[{"id": ' + "9" * 5001 + ', "label": "a", "template": "Pushing [something] from left to right"}]',
     r"train.json: JSON that Python cannot read \(ValueError: Exceeds the limit \(4300 digits\)"),
    ("train", "[" * 100_000 + "]" * 100_000, r"train.json: JSON that Python cannot read \(RecursionError"),
], ids=["lone-surrogate", "class-named-twice", "field-twice", "huge-number", "deep-nesting"])
def test_text_json_takes_but_nothing_can_use_is_refused_naming_it(annotations, name, text, message):
    """A lone surrogate went into the shards (preview then died with SIGSEGV in OpenCV's putText; as an id, the build
    raised UnicodeEncodeError); of a key given twice, JSON keeps the last without a word (a class lost its clips)."""
    (annotations / f"something-something-v2-{name}.json").write_text(text)
    with pytest.raises(AnnotationError, match=message):
        load_split(annotations, "train")


def test_class_name_strips_only_the_brackets():
    assert class_name("Putting [something] onto [a slanted surface]") == "Putting something onto a slanted surface"
    assert class_name("Tipping [something] with [something in it] over, so [something in it] falls out") == \
        "Tipping something with something in it over, so something in it falls out"


def test_train_records_get_class_index_caption_and_template(annotations):
    records = load_split(annotations, "train")
    assert [r.id for r in records] == ["78687", "42326", "3"]  # the file's order
    assert [r.class_index for r in records] == [0, 1, 2]
    assert records[1].caption == "tipping cup with water in it over, so water falls out"
    assert records[1].template.startswith("Tipping [something] with [something in it]")


def test_test_split_has_no_labels_and_needs_no_label_file(annotations):
    (annotations / "something-something-v2-labels.json").unlink()
    records = load_split(annotations, "test")
    assert [(r.id, r.class_index, r.caption, r.template) for r in records] == \
        [("1420", NO_LABEL, "", ""), ("55", NO_LABEL, "", "")]


def test_unknown_template_and_missing_file_give_clear_errors(annotations):
    entry = {"id": "9", "label": "x", "template": "Juggling [something]", "placeholders": []}
    write(annotations, "validation", [entry])
    with pytest.raises(AnnotationError, match="Juggling something.*labels.json"):
        load_split(annotations, "validation")
    (annotations / "something-something-v2-train.json").unlink()
    with pytest.raises(AnnotationError, match="train.json: file not found"):
        load_split(annotations, "train")
    assert load_labels(annotations)["Pushing something from left to right"] == 2


@pytest.mark.parametrize("split", ["train", "test"])
def test_a_repeated_id_or_an_entry_without_one_is_refused_by_position(annotations, split):
    entries = json.loads((annotations / f"something-something-v2-{split}.json").read_text())
    write(annotations, split, entries + [entries[0]])
    with pytest.raises(AnnotationError, match=rf"{split}.json: entries 0 and {len(entries)} both have id "
                                              rf"'{entries[0]['id']}'; each clip must appear once"):
        load_split(annotations, split)
    write(annotations, split, entries + [{"label": "no id"}])
    with pytest.raises(AnnotationError, match=rf"{split}.json: entry {len(entries)} is not an object with an \"id\""):
        load_split(annotations, split)


@pytest.mark.parametrize("change, message", [
    ({"template": None}, r"entry 0 \(id '78687'\): field 'template' must be a string, got null"),
    ({"label": 7}, r"entry 0 \(id '78687'\): field 'label' must be a string, got 7"),
    ({"id": None}, r"entry 0 has id null; an id must be a string or a whole number"),
    ({"id": True}, r"entry 0 has id true"),
])
def test_a_field_of_the_wrong_type_is_refused_with_the_entry_and_the_field(annotations, change, message):
    entries = json.loads((annotations / "something-something-v2-train.json").read_text())
    write(annotations, "train", [entries[0] | change] + entries[1:])
    with pytest.raises(AnnotationError, match=message):
        load_split(annotations, "train")


def test_a_missing_caption_is_named_as_missing_not_as_an_unknown_class(annotations):
    entries = json.loads((annotations / "something-something-v2-train.json").read_text())
    del entries[2]["label"]
    write(annotations, "train", entries)
    with pytest.raises(AnnotationError, match=r"entry 2 \(id '3'\) has no field 'label'"):
        load_split(annotations, "train")


@pytest.mark.parametrize("index", ["two", [2], True, -1, "-1", "²", "٣"],  # -1 marks test clips; "²".isdigit()
                         ids=["word", "list", "bool", "negative-int", "negative-text", "superscript", "arabic-digit"])
def test_a_class_index_that_is_not_a_whole_number_is_refused(annotations, index):
    labels = json.loads((annotations / "something-something-v2-labels.json").read_text())
    write(annotations, "labels", labels | {"Pushing something from left to right": index})
    with pytest.raises(AnnotationError, match=r"labels.json: class 'Pushing something from left to right' has index "
                                              r".*; an index must be a whole number ≥ 0"):
        load_labels(annotations)


@pytest.mark.parametrize(("index", "message"), [
    ("99999999999999999999999", r"has index 99999999999999999999999, more than 2147483647: number the classes"),
    ("0", r"classes .* and 'Pushing something from left to right' share index 0; each class needs its own"),
])
def test_a_class_index_too_large_or_shared_is_refused(annotations, index, message):
    labels = json.loads((annotations / "something-something-v2-labels.json").read_text())
    write(annotations, "labels", labels | {"Pushing something from left to right": index})
    with pytest.raises(AnnotationError, match=message):
        load_labels(annotations)
