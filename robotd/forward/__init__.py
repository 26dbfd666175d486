"""The forward loop detector (paper 000, Angeli et al. 2008; algorithm layer, no I/O):
local features, an incremental vocabulary with an inverted index, tf-idf voting, a Bayes
filter over loop hypotheses and epipolar verification; optionally a working memory that
bounds the per-image time."""

from robotd.forward.detector import (LOOP, LOW_POSTERIOR, METHODS, NO_GEOMETRIC_CONSISTENCY, NO_HYPOTHESES,
                                     NOT_CONSISTENT_YET, method_params,
                                     STAGES, Detection, DetectorParams, ForwardDetector)
from robotd.forward.features import FeatureExtractor, FeatureParams, Features, extract_features
from robotd.forward.filter import FilterParams
from robotd.forward.memory import MemoryParams, WorkingMemory
from robotd.forward.verify import Verification, VerifyParams, verify_pair
from robotd.forward.vocabulary import InvertedIndex, Vocabulary, VocabularyParams

__all__ = [
    "Detection", "DetectorParams", "FeatureExtractor", "FeatureParams", "Features", "FilterParams",
    "ForwardDetector", "MemoryParams", "WorkingMemory", "InvertedIndex", "LOOP", "LOW_POSTERIOR", "NO_GEOMETRIC_CONSISTENCY",
    "NO_HYPOTHESES", "STAGES", "Verification", "VerifyParams", "Vocabulary", "VocabularyParams",
    "extract_features", "verify_pair", "METHODS", "NOT_CONSISTENT_YET", "method_params",
]
