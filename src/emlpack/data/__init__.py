"""Datasets: the HDF5 store (:mod:`emlpack.data.store`), torch datasets and augmentation."""
