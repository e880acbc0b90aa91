"""One search for every frame (issue 45): candidates from named proposals (:mod:`.candidates`),
fitted as one batch (:mod:`.fit`), one score (:mod:`.score`) picks the answer; a new track's search
from the hand found in the depth to its finalists: :mod:`.start`."""

from hand_sog_tracker.core.search.candidates import NEW_TRACK_PROPOSALS, TRACK_PROPOSALS, Candidate, Frame, Proposal
from hand_sog_tracker.core.search.fit import SEARCH_ITERATIONS, search
from hand_sog_tracker.core.search.score import ASSIGN_LAMBDA_MM, assignment_cost, plain

__all__ = [
    "ASSIGN_LAMBDA_MM", "Candidate", "Frame", "NEW_TRACK_PROPOSALS", "Proposal", "SEARCH_ITERATIONS",
    "TRACK_PROPOSALS", "assignment_cost", "plain", "search",
]
