"""The residual loop's named thresholds (``residual``'s docstring says what each stage decides with them).
Nothing here imports ROS."""

__all__ = ["CAPACITY_OPERATORS", "CAPACITY_EXTENSION", "MID_CAPACITY", "CAPACITY_TOLERANCE", "CAPACITY_REVISIT",
           "PLACEMENT_SHIFT_SHARE", "TREND_DOMINANCE", "CAPACITY_TREND_DEGREE", "INITIAL_STATE_TOLERANCE",
           "WIPE_GAIN", "HELD_OUT_RANGE_MARGIN", "KNOWN_MIN_SHARE", "RESOLUTION_SHARE", "UNEXPLAINED_NOISE_RATIO",
           "PEAK_NOISE_RATIO", "START_MOTION_MAX_S", "START_MOTION_MAX_SHARE", "START_MOTION_FIRST_ROWS",
           "START_MOTION_RATIO", "MAD_TO_SIGMA", "SPREAD_SHARE", "PEAK_BLOCK_S", "PEAK_RANK", "MIN_STRUCTURE_PCT",
           "CONFIRM_ROUNDS", "SEPARATION_SHARE", "EXACT_CHECK_GAIN", "EXACT_ALL_ROWS", "DELAY_STEPS", "SEARCH_TRUST"]

CAPACITY_OPERATORS = (12, 18, 27, 40, 60)   # GPIM sizes tried for the baseline
CAPACITY_EXTENSION = (90, 135)              # ... then these, one at a time, while the largest so far is the best
                                            # by more than CAPACITY_TOLERANCE over the size below it
MID_CAPACITY = 27                           # the size G_v's poles are first fitted with
CAPACITY_TOLERANCE = 0.02                   # a smaller GPIM within 2 % of the best held-out RMS is preferred
CAPACITY_REVISIT = 0.05                     # a smaller size within this share of the chosen one's score is a
                                            # knife edge: the effects are chosen again on it (_Loop.revisit_capacity)
PLACEMENT_SHIFT_SHARE = 0.5                 # an asymmetry whose shift is at least this share of its envelope's
                                            # departure may be the thresholds' placement: it is tried
                                            # (_Loop.revisit_placement)
TREND_DOMINANCE = 0.5                       # when the best size's held-out error about its quadratic trend is
                                            # below this share of its RMS, a trend (a drift) swamps what the
                                            # sizes differ in, and they are compared about their trends
CAPACITY_TREND_DEGREE = 2                   # ... of this degree in time
INITIAL_STATE_TOLERANCE = 0.02              # "cycled" replaces "rest" only if it cuts the held-out RMS by more
WIPE_GAIN = 0.1                             # fitting only after the wipe must cut the held-out RMS by >= 10 %
HELD_OUT_RANGE_MARGIN = 0.05                # held-out data driven beyond the fit part's voltage range by more
                                            # than this share of it: warned (the fit cannot know that range)
KNOWN_MIN_SHARE = 0.1                       # ... and where they leave it after this share of their rows, an effect
                                            # must not do worse on the rows before (search.support)
RESOLUTION_SHARE = 1e-6                     # a record's noise is taken as at least this share of its range
UNEXPLAINED_NOISE_RATIO = 2.0               # structured residual RMS above this many noise RMS: unexplained
PEAK_NOISE_RATIO = 2.5                      # held-out peaks above this many times the noise's: unexplained
START_MOTION_MAX_S = 0.1                    # a validation session's start in motion: within its first this long ...
START_MOTION_MAX_SHARE = 0.01               # ... and this share of it ...
START_MOTION_FIRST_ROWS = 3                 # ... starting within its first rows ...
START_MOTION_RATIO = 5.0                    # ... the rows whose error stands this many spreads off are left out
MAD_TO_SIGMA = 1.4826                       # the median absolute deviation of a normal variable times this: its sigma
SPREAD_SHARE = 0.5                          # a held-out RMS of this share of the held-out output's own standard
                                            # deviation (a fit of 50 % or less) is unexplained, whatever else
PEAK_BLOCK_S = 0.005                        # ... judged on the PEAK_RANK-th largest peak of blocks this long
PEAK_RANK = 3
MIN_STRUCTURE_PCT = 0.01                    # ... and above this % of the range (noise-free records)
CONFIRM_ROUNDS = 4                          # exact drop-one rounds at most
SEPARATION_SHARE = 0.8                       # an effect that does this share of an added one's work in its
                                            # place: the record cannot tell the two apart (reported)
EXACT_CHECK_GAIN = 0.05                     # effects the linear search credits with >= 5 % are checked exactly ...
EXACT_ALL_ROWS = 20000                      # ... every effect, on a fit record of at most this many rows ...
DELAY_STEPS = (-2, -1, 1, 2, 3)             # a dead time chosen on held-out data: the fitted one and these many
                                            # analysis samples from it
SEARCH_TRUST = 0.2                          # ... or where the exact refit of its set does worse than its figure by more
                                            # than this share, or delivers less than 1 - this of the cut it promised
