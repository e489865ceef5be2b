"""The guidance model: the paper's LSTM (:mod:`~dhg.learning.network`) and its presets
(:mod:`~dhg.learning.presets`), training (:mod:`~dhg.learning.train`), the TorchScript model file
(:mod:`~dhg.learning.torchscript`), demonstration profiles (:mod:`~dhg.learning.profiles`),
feature ablation (:mod:`~dhg.learning.ablation`) and the bundled weights
(:mod:`~dhg.learning.weights`)."""
