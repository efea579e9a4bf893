"""The guardian's reading of its owner's pipe (rigctl.rigs.guardian), with no process: a pipe is the
bytes the owner wrote before it closed. Only a complete `ended` line as the last word is a normal
end; the rig and the bench's pid are taken as they come."""

from __future__ import annotations

import io

from rigctl.rigs.guardian import ended_normally, owner_words


class Ward:
    """What the guardian would guard: the words it was given, in order."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, object]] = []

    def arm(self, rig_json: str) -> None:
        self.calls.append(("arm", rig_json))

    def bench(self, pid: int) -> None:
        self.calls.append(("bench", pid))


def follow(written: bytes) -> tuple[bool, list]:
    ward = Ward()
    return ended_normally(owner_words(io.BytesIO(written)), ward), ward.calls


def test_the_word_ended_before_the_pipe_closes_is_a_normal_end():
    ended, calls = follow(b'rig {"rig": {"kind": "six-coil"}}\nbench 4242\nended\n')
    assert ended
    assert calls == [("arm", '{"rig": {"kind": "six-coil"}}'), ("bench", 4242)]


def test_a_pipe_closed_without_the_word_is_the_owner_gone():
    ended, calls = follow(b'rig {"a": 1}\n')
    assert not ended
    assert calls == [("arm", '{"a": 1}')]


def test_a_word_cut_off_by_the_owners_death_is_no_word():
    assert not follow(b"rig {}\nend")[0]
    assert not follow(b"rig {}\nended")[0]  # its newline never came: not known to be complete


def test_a_pipe_closed_before_anything_was_said_is_not_a_normal_end():
    assert follow(b"") == (False, [])


def test_only_the_last_word_counts():
    # an owner that took a rig again after saying it ended (one guardian per owner's life)
    ended, calls = follow(b"rig {}\nended\nrig {}\n")
    assert not ended
    assert calls == [("arm", "{}"), ("arm", "{}")]
