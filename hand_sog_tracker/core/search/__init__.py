"""One search for every frame (issue 45): candidates from named proposals, fitted as one batch,
one score picks the answer.

- :mod:`.candidates`: :class:`Frame` (what the proposals look at), :class:`Candidate`,
  :class:`Proposal` and the proposals of a tracked frame and of a new track;
- :mod:`.fit`: :func:`search`, the batch fit and the selection;
- :mod:`.score`: the score (the objective without its salient term minus the detections'
  assignment cost, seed 001 eq. 11);
- :mod:`.start`: a new track's search, from the hand found in the depth to its finalists.
"""

from hand_sog_tracker.core.search.candidates import NEW_TRACK_PROPOSALS, TRACK_PROPOSALS, Candidate, Frame, Proposal
from hand_sog_tracker.core.search.fit import SEARCH_ITERATIONS, search
from hand_sog_tracker.core.search.score import ASSIGN_LAMBDA_MM, assignment_cost, plain

__all__ = [
    "ASSIGN_LAMBDA_MM", "Candidate", "Frame", "NEW_TRACK_PROPOSALS", "Proposal", "SEARCH_ITERATIONS",
    "TRACK_PROPOSALS", "assignment_cost", "plain", "search",
]
