"""The bounding sphere hierarchy (§5.1, §5.4): the build-bsh stage, the tree builder and its kernels, the 40-byte node format."""
