"""The models: RBF SVMs on features or raw blocks (`estimators`, `gram`), Algorithm 1's
queries and loop (`query`, `active`), grouped cross-validation (`cv`), the transfer-learning
baselines (`transfer`), the feature base's pre-training (`pretrain`) and model bundles
(`bundle`, `bundle_check`).
"""
