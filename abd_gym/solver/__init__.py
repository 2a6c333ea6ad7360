"""The implicit step: the Newton solve of the incremental potential (``solver``), its kernels, the
fused one-launch step (``fused``) and the execution plan that picks how it runs on a device."""
