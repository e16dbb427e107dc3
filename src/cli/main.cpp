#include <cstdio>
int main() { std::puts("scandyn"); return 0; }
